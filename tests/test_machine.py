"""What this machine can do (``tracegs.machine``): read once, asked by every other module, recorded once
in a run's summary."""

import json
import os
import subprocess
import sys

import torch

from tracegs.machine import ISA_ENVIRONMENTS, Machine, resolve_device, this_machine


def _cpuinfo(tmp_path, name: str, flags: str) -> str:
    path = tmp_path / name
    path.write_text(
        f"processor\t: 0\nmodel name\t: X(R) Y\nflags\t\t: {flags}\n\nprocessor\t: 1\nflags\t\t: {flags}\n"
    )
    return str(path)


def test_hardware_bf16_is_read_from_the_cpu_flags(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX512")

    def fast(name, flags):
        return Machine.read(_cpuinfo(tmp_path, name, flags)).fast_bf16

    assert not fast("avx2", "fpu sse2 avx avx2 fma")
    assert not fast("avx512", "avx2 avx512f avx512bw avx512_vnni")
    assert fast("zen4", "avx2 avx512f avx512_bf16")
    assert fast("spr", "avx2 avx512f avx512_bf16 amx_bf16 amx_tile")
    assert not Machine.read(tmp_path / "missing").fast_bf16
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")  # (ATen held to AVX2)
    assert not fast("zen4", "avx2 avx512f avx512_bf16")


def test_the_description_names_the_cores_the_model_and_the_extensions(tmp_path):
    machine = Machine.read(_cpuinfo(tmp_path, "zen4", "avx2 avx512f avx512_bf16"))
    assert machine.cpu == "X Y" and machine.features == ["AVX2", "AVX-512", "AVX512-BF16"]
    cores = f"{machine.cores} core{'s' if machine.cores != 1 else ''}"
    assert machine.description == f"{cores}, X Y (AVX2, AVX-512, AVX512-BF16)"
    assert json.loads(json.dumps(machine.record()))["description"] == machine.description


def test_a_process_held_below_avx512_has_no_fast_bf16():
    """``ATEN_CPU_CAPABILITY=avx2`` (``--isa avx2``) runs as an AVX2-only CPU: fp32 fields, and the
    ``cpu-fast`` preset made there asks for none."""
    code = (
        "import json; from tracegs.machine import this_machine; from tracegs.config import make_config; "
        "print(json.dumps([this_machine().record(), make_config('cpu-fast').bf16]))"
    )
    env = {**os.environ, **ISA_ENVIRONMENTS["avx2"]}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    record, preset_bf16 = json.loads(out.stdout.strip().splitlines()[-1])
    assert not record["isa"].upper().startswith("AVX512") and not record["fast_bf16"] and not preset_bf16
    assert record["march"] == "x86-64-v3"


def test_this_machine_is_read_once_and_decides_the_device_and_the_threads():
    from tracegs.train.threads import ThreadPolicy

    machine = this_machine()
    assert this_machine() is machine
    assert resolve_device("auto").type == machine.device
    assert machine.fast_bf16 == (
        bool(machine.flags & {"amx_bf16", "avx512_bf16"}) and machine.isa.upper().startswith("AVX512")
    )
    policy = ThreadPolicy()
    assert policy.most == machine.threads and policy.cpus == set(machine.cpus)


def test_a_run_records_the_machine_once_in_its_summary(tiny_scene, tmp_path):
    from tracegs.config import make_config
    from tracegs.train.trainer import Trainer

    cfg = make_config("tiny", data=tiny_scene, run=tmp_path / "run", device="cpu")
    summary = json.loads(json.dumps(Trainer(cfg, progress=False).summary()))
    assert summary["machine"] == this_machine().record()
    repeated = set(this_machine().record()) - {"device", "threads"}  # (the run's own: its device, its counts)
    assert not repeated & set(summary)
