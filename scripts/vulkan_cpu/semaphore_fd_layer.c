/*
 * VK_LAYER_IDR_semaphore_fd: lets SAPIEN 2's renderer start on Mesa's lavapipe (Vulkan on the CPU).
 *
 * SAPIEN 2.2 (svulkan2) requires the device extension VK_KHR_external_semaphore_fd when it creates
 * its device; it uses it only to share semaphores with CUDA, which a CPU renderer never does.
 * Lavapipe (Mesa 25) lacks it, so device creation fails with VK_ERROR_EXTENSION_NOT_PRESENT. This
 * layer lists the extension among the device's extensions and removes it from vkCreateDevice's
 * request when the driver lacks it; every other call goes straight to the next layer or driver.
 * A program that then called vkGetSemaphoreFdKHR would get NULL from vkGetDeviceProcAddr.
 *
 * Built by scripts/setup_vulkan_cpu.sh; enabled with VK_LAYER_PATH and VK_INSTANCE_LAYERS.
 */
#include <pthread.h>
#include <stdlib.h>
#include <string.h>
#include <vulkan/vk_layer.h>
#include <vulkan/vulkan.h>

#define LAYER_NAME "VK_LAYER_IDR_semaphore_fd"
#define MAX_OBJECTS 64

static const char *const ADDED = VK_KHR_EXTERNAL_SEMAPHORE_FD_EXTENSION_NAME;

/* The next layer's entry points, per instance and per device, keyed by the loader's dispatch
   key (the first pointer of a dispatchable handle; a physical device shares its instance's). */
typedef struct {
    void *key;
    PFN_vkGetInstanceProcAddr gipa;
    PFN_vkGetDeviceProcAddr gdpa;
    PFN_vkEnumerateDeviceExtensionProperties enumerate;
} Next;

static Next instances[MAX_OBJECTS], devices[MAX_OBJECTS];
static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;

static void *key_of(const void *handle) { return *(void *const *)handle; }

static Next *find(Next *table, void *key) {
    for (int i = 0; i < MAX_OBJECTS; i++)
        if (table[i].key == key) return &table[i];
    return NULL;
}

static int store(Next *table, Next entry) {
    pthread_mutex_lock(&lock);
    Next *slot = find(table, entry.key);
    if (!slot) slot = find(table, NULL);
    if (slot) *slot = entry;
    pthread_mutex_unlock(&lock);
    return slot != NULL;
}

static Next lookup(Next *table, void *key) {
    Next out = {0};
    pthread_mutex_lock(&lock);
    Next *slot = find(table, key);
    if (slot) out = *slot;
    pthread_mutex_unlock(&lock);
    return out;
}

static VKAPI_ATTR VkResult VKAPI_CALL CreateInstance(const VkInstanceCreateInfo *info,
                                                     const VkAllocationCallbacks *alloc,
                                                     VkInstance *instance) {
    VkLayerInstanceCreateInfo *link = (VkLayerInstanceCreateInfo *)info->pNext;
    while (link && !(link->sType == VK_STRUCTURE_TYPE_LOADER_INSTANCE_CREATE_INFO &&
                     link->function == VK_LAYER_LINK_INFO))
        link = (VkLayerInstanceCreateInfo *)link->pNext;
    if (!link) return VK_ERROR_INITIALIZATION_FAILED;
    PFN_vkGetInstanceProcAddr gipa = link->u.pLayerInfo->pfnNextGetInstanceProcAddr;
    link->u.pLayerInfo = link->u.pLayerInfo->pNext; /* the next layer finds its own link */
    PFN_vkCreateInstance create = (PFN_vkCreateInstance)gipa(VK_NULL_HANDLE, "vkCreateInstance");
    VkResult result = create(info, alloc, instance);
    if (result != VK_SUCCESS) return result;
    Next next = {key_of(*instance), gipa, NULL,
                 (PFN_vkEnumerateDeviceExtensionProperties)gipa(
                     *instance, "vkEnumerateDeviceExtensionProperties")};
    return store(instances, next) ? VK_SUCCESS : VK_ERROR_TOO_MANY_OBJECTS;
}

/* The driver's extensions of a physical device (malloc'd; NULL on failure). */
static VkExtensionProperties *driver_extensions(VkPhysicalDevice gpu, uint32_t *count) {
    Next next = lookup(instances, key_of(gpu));
    if (!next.enumerate || next.enumerate(gpu, NULL, count, NULL) != VK_SUCCESS) return NULL;
    VkExtensionProperties *props = calloc(*count + 1, sizeof *props);
    if (props && next.enumerate(gpu, NULL, count, props) != VK_SUCCESS) {
        free(props);
        return NULL;
    }
    return props;
}

static int has(const VkExtensionProperties *props, uint32_t n, const char *name) {
    for (uint32_t i = 0; i < n; i++)
        if (strcmp(props[i].extensionName, name) == 0) return 1;
    return 0;
}

static VKAPI_ATTR VkResult VKAPI_CALL EnumerateDeviceExtensionProperties(
    VkPhysicalDevice gpu, const char *layer, uint32_t *count, VkExtensionProperties *out) {
    if (layer && strcmp(layer, LAYER_NAME) == 0) { /* the layer implements none itself */
        *count = 0;
        return VK_SUCCESS;
    }
    if (layer) return lookup(instances, key_of(gpu)).enumerate(gpu, layer, count, out);
    uint32_t n = 0;
    VkExtensionProperties *props = driver_extensions(gpu, &n);
    if (!props) return VK_ERROR_INITIALIZATION_FAILED;
    if (!has(props, n, ADDED)) {
        strncpy(props[n].extensionName, ADDED, VK_MAX_EXTENSION_NAME_SIZE - 1);
        props[n].specVersion = 1;
        n++;
    }
    VkResult result = VK_SUCCESS;
    if (!out) {
        *count = n;
    } else {
        if (*count < n) result = VK_INCOMPLETE;
        else *count = n;
        memcpy(out, props, *count * sizeof *props);
    }
    free(props);
    return result;
}

static VKAPI_ATTR VkResult VKAPI_CALL CreateDevice(VkPhysicalDevice gpu,
                                                   const VkDeviceCreateInfo *info,
                                                   const VkAllocationCallbacks *alloc,
                                                   VkDevice *device) {
    VkLayerDeviceCreateInfo *link = (VkLayerDeviceCreateInfo *)info->pNext;
    while (link && !(link->sType == VK_STRUCTURE_TYPE_LOADER_DEVICE_CREATE_INFO &&
                     link->function == VK_LAYER_LINK_INFO))
        link = (VkLayerDeviceCreateInfo *)link->pNext;
    if (!link) return VK_ERROR_INITIALIZATION_FAILED;
    PFN_vkGetInstanceProcAddr gipa = link->u.pLayerInfo->pfnNextGetInstanceProcAddr;
    PFN_vkGetDeviceProcAddr gdpa = link->u.pLayerInfo->pfnNextGetDeviceProcAddr;
    link->u.pLayerInfo = link->u.pLayerInfo->pNext;
    PFN_vkCreateDevice create = (PFN_vkCreateDevice)gipa(VK_NULL_HANDLE, "vkCreateDevice");

    uint32_t n = 0;
    VkExtensionProperties *props = driver_extensions(gpu, &n);
    if (!props) return VK_ERROR_INITIALIZATION_FAILED;
    int drop = !has(props, n, ADDED);
    free(props);
    VkDeviceCreateInfo copy = *info;
    const char **names = calloc(info->enabledExtensionCount + 1, sizeof *names);
    if (!names) return VK_ERROR_OUT_OF_HOST_MEMORY;
    uint32_t kept = 0;
    for (uint32_t i = 0; i < info->enabledExtensionCount; i++)
        if (!(drop && strcmp(info->ppEnabledExtensionNames[i], ADDED) == 0))
            names[kept++] = info->ppEnabledExtensionNames[i];
    copy.enabledExtensionCount = kept;
    copy.ppEnabledExtensionNames = names;
    VkResult result = create(gpu, &copy, alloc, device);
    free(names);
    if (result != VK_SUCCESS) return result;
    Next next = {key_of(*device), NULL, gdpa, NULL};
    return store(devices, next) ? VK_SUCCESS : VK_ERROR_TOO_MANY_OBJECTS;
}

static VKAPI_ATTR PFN_vkVoidFunction VKAPI_CALL GetDeviceProcAddr(VkDevice device,
                                                                  const char *name) {
    if (strcmp(name, "vkGetDeviceProcAddr") == 0) return (PFN_vkVoidFunction)GetDeviceProcAddr;
    PFN_vkGetDeviceProcAddr next = lookup(devices, key_of(device)).gdpa;
    return next ? next(device, name) : NULL;
}

static VKAPI_ATTR PFN_vkVoidFunction VKAPI_CALL GetInstanceProcAddr(VkInstance instance,
                                                                    const char *name);

static PFN_vkVoidFunction own(const char *name) {
    if (strcmp(name, "vkGetInstanceProcAddr") == 0) return (PFN_vkVoidFunction)GetInstanceProcAddr;
    if (strcmp(name, "vkGetDeviceProcAddr") == 0) return (PFN_vkVoidFunction)GetDeviceProcAddr;
    if (strcmp(name, "vkCreateInstance") == 0) return (PFN_vkVoidFunction)CreateInstance;
    if (strcmp(name, "vkCreateDevice") == 0) return (PFN_vkVoidFunction)CreateDevice;
    if (strcmp(name, "vkEnumerateDeviceExtensionProperties") == 0)
        return (PFN_vkVoidFunction)EnumerateDeviceExtensionProperties;
    return NULL;
}

static VKAPI_ATTR PFN_vkVoidFunction VKAPI_CALL GetInstanceProcAddr(VkInstance instance,
                                                                    const char *name) {
    PFN_vkVoidFunction mine = own(name);
    if (mine) return mine;
    if (instance == VK_NULL_HANDLE) return NULL;
    PFN_vkGetInstanceProcAddr next = lookup(instances, key_of(instance)).gipa;
    return next ? next(instance, name) : NULL;
}

VK_LAYER_EXPORT VKAPI_ATTR VkResult VKAPI_CALL
vkNegotiateLoaderLayerInterfaceVersion(VkNegotiateLayerInterface *interface) {
    if (interface->loaderLayerInterfaceVersion > 2) interface->loaderLayerInterfaceVersion = 2;
    interface->pfnGetInstanceProcAddr = GetInstanceProcAddr;
    interface->pfnGetDeviceProcAddr = GetDeviceProcAddr;
    interface->pfnGetPhysicalDeviceProcAddr = NULL;
    return VK_SUCCESS;
}
