"""The hardware record names this machine as its own tools do: the CPU model as /proc/cpuinfo
says it, the instruction set torch dispatches to, the library versions torch was built with,
the pins in the environment, and the renderer an actor would use."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from workers.hardware import hardware_class, hardware_record, renderer_in_child


def test_the_record_names_this_cpu_its_instruction_set_and_libraries(monkeypatch) -> None:
    monkeypatch.setenv("MKL_CBWR", "AVX2")
    rec = hardware_record("cpu")
    info = Path("/proc/cpuinfo")
    if info.is_file():
        names = {
            line.split(":", 1)[1].strip()
            for line in info.read_text().splitlines()
            if line.startswith("model name")
        }
        assert rec["cpu_model"] in names
    assert rec["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert rec["torch"] == torch.__version__ and rec["torch_threads"] == torch.get_num_threads()
    assert rec["isa_pins"] == {"MKL_CBWR": "AVX2"}
    assert rec["gpu"] is None  # the model computes on the CPU: no GPU in its class
    if torch.backends.mkldnn.is_available():
        assert rec["onednn"] and rec["onednn"][0].isdigit()
    assert hardware_class(rec) == f"{rec['cpu_model']} / {rec['cpu_capability']}"


def test_a_gpu_joins_the_class_with_its_compute_capability() -> None:
    rec = {"cpu_model": "AMD EPYC", "cpu_capability": "AVX2", "gpu": "NVIDIA H200"}
    assert (
        hardware_class({**rec, "gpu_capability": "9.0"}) == "AMD EPYC / AVX2 / NVIDIA H200 (sm 9.0)"
    )
    assert hardware_class({"cpu_model": None}) == "unknown / unknown"


@pytest.mark.sim
def test_the_renderer_is_read_as_an_actor_would_render() -> None:
    renderer = renderer_in_child()
    assert renderer is not None and " / " in renderer
    assert "llvmpipe" in renderer or "NVIDIA" in renderer  # OSMesa on a CPU box, EGL on a GPU
