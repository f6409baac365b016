"""Training that is safe to leave running: a run killed with SIGKILL (during densification, at a
checkpoint, while a checkpoint is written, during the calibration) and started again ends exactly where
an uninterrupted run ends; Ctrl-C saves the step reached; the NaN guard restores the last good state."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from tests.conftest import write_tiny_scene

import tracegs.train.losses as losses_module
import tracegs.train.trainer as trainer_module
from tracegs.config import make_config
from tracegs.run import (
    CHECKPOINT,
    EXTRAPOLATION,
    LOCK,
    LOG,
    RunError,
    TrainingDiverged,
    load_tensors,
    lock_run,
)
from tracegs.train.trainer import Trainer

SETTINGS = {
    "device": "cpu",
    "static_iterations": 4,
    "dynamic_iterations": 8,
    "init_points": 300,
    "checkpoint_every": 3,  # after steps 3, 6, 9 and 12
    "log_every": 1,
    # densification refines at steps 2, 4, 6; skip_static (tiny) marks the static Gaussians at step 8
    "densify.refine_every": 2,
    "densify.refine_stop": 8,
    "densify.refine_stop_fraction": 1.0,
}
TOTAL = SETTINGS["static_iterations"] + SETTINGS["dynamic_iterations"]

# Trains the run of SETTINGS in a fresh process with one thread (as the tests do) and SIGKILLs itself
# at the point that argv names: inside the densification of a step, at the start of a step, halfway
# through the n-th write of the checkpoint, or in the calibration.
KILLED_RUN = """
import json, os, signal, sys
from pathlib import Path
import torch
torch.set_num_threads(1)
from tracegs.config import make_config
import tracegs.train.trainer as T

args = json.loads(sys.argv[1])
where, at = args["kill"], args["at"]

def die(*_):
    os.kill(os.getpid(), signal.SIGKILL)

if where == "densify":
    post = T.DefaultStrategy.step_post_backward
    def killing_post(self, params, optimizers, state, step, info):
        if step == at:  # after the step's optimiser update, in its densification
            die()
        return post(self, params, optimizers, state, step, info)
    T.DefaultStrategy.step_post_backward = killing_post
elif where == "step":
    step = T.Trainer.train_step
    def killing_step(self):
        if self.state.step == at:
            die()
        return step(self)
    T.Trainer.train_step = killing_step
elif where == "save":
    write = Path.write_bytes
    writes = []
    def killing_write(self, data):
        if self.name.startswith(".checkpoint.pt."):
            writes.append(self)
            if len(writes) == at:
                write(self, data[: len(data) // 2])
                die()
        return write(self, data)
    Path.write_bytes = killing_write
elif where == "calibrate":
    T.calibrate = die
T.Trainer(make_config("tiny", **args["settings"]), progress=False).train()
"""


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("resume") / "scene")


@pytest.fixture
def one_thread():
    """One thread, as the killed runs have: then every run of the same settings is bitwise the same."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def settings(scene: Path, run: Path, **changes) -> dict:
    return {**SETTINGS, "data": str(scene), "run": str(run), **changes}


def train(scene: Path, run: Path, **changes) -> Trainer:
    trainer = Trainer(make_config("tiny", **settings(scene, run, **changes)), progress=False)
    trainer.train()
    return trainer


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory) -> Path:
    """The run trained without interruption (one thread)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        run = tmp_path_factory.mktemp("reference") / "run"
        train(scene, run)
    finally:
        torch.set_num_threads(threads)
    return run


def killed_run(scene: Path, run: Path, kill: str, at: int) -> None:
    args = json.dumps({"settings": settings(scene, run), "kill": kill, "at": at})
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-c", KILLED_RUN, args], env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == -signal.SIGKILL, done.stderr


def test_a_run_killed_from_outside_at_a_random_step_resumes_to_the_same_parameters(
    scene, tmp_path, one_thread
):
    """The kill lands wherever the run is (in a step, a checkpoint write, a log line): every moment
    must resume to the uninterrupted run's parameters."""
    longer = {"dynamic_iterations": 36, "checkpoint_every": 7}
    target = random.randrange(1, 36)
    run = tmp_path / "run"
    args = json.dumps({"settings": settings(scene, run, **longer), "kill": None, "at": None})
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    process = subprocess.Popen([sys.executable, "-c", KILLED_RUN, args], env=env, stderr=subprocess.PIPE)
    while process.poll() is None and not (
        (run / LOG).is_file() and len((run / LOG).read_text().splitlines()) >= target
    ):
        time.sleep(0.005)
    process.kill()  # SIGKILL
    process.communicate(timeout=60)
    saved = load_tensors(run / CHECKPOINT)["step"] if (run / CHECKPOINT).is_file() else 0
    train(scene, run, **longer)
    train(scene, tmp_path / "reference", **longer)
    assert_same_run(run, tmp_path / "reference", f"killed once step {target} was logged, resumed at {saved}")


def flat(value, prefix: str = "") -> dict:
    """Every tensor and number of a checkpoint's (nested) data by its dotted key."""
    if isinstance(value, dict):
        return {k: v for key, item in value.items() for k, v in flat(item, f"{prefix}{key}.").items()}
    if isinstance(value, (list, tuple)):
        return {k: v for i, item in enumerate(value) for k, v in flat(item, f"{prefix}{i}.").items()}
    return {prefix.rstrip("."): value}


def largest_difference(a: Path, b: Path, skip=("train_seconds", "timings", "config")) -> float:
    """The largest absolute difference between two ``.pt`` files' tensors, after checking that they
    hold the same keys, shapes and plain values (wall times and the run's paths aside)."""
    x, y = (flat({k: v for k, v in load_tensors(p).items() if k not in skip}) for p in (a, b))
    assert x.keys() == y.keys()
    largest = 0.0
    for key, u in x.items():
        v = y[key]
        if isinstance(u, torch.Tensor):
            assert u.shape == v.shape and u.dtype == v.dtype, key
            if u.numel() and u.dtype != torch.bool:
                largest = max(largest, float((u.double() - v.double()).abs().max()))
            else:
                assert torch.equal(u, v), key
        else:
            assert u == v, key
    return largest


def logged(run: Path) -> list[tuple[int, float]]:
    return [(r["step"], r["loss"]) for r in map(json.loads, (run / LOG).read_text().splitlines())]


def assert_same_run(run: Path, reference: Path, note: str = "") -> None:
    # bitwise here (one thread on a CPU); 1e-6 is what the issue allows
    assert largest_difference(run / CHECKPOINT, reference / CHECKPOINT) <= 1e-6, note
    assert largest_difference(run / EXTRAPOLATION, reference / EXTRAPOLATION) <= 1e-6, note
    assert logged(run) == logged(reference), note  # each step logged once, with the same loss


@pytest.mark.parametrize(
    "kill, at, resumes_at",
    [
        ("densify", 6, 6),  # in the refinement of step 6: statistics of step 5 are in checkpoint 6
        ("step", 9, 9),  # right after checkpoint 9, with the static Gaussians just marked (step 8)
        ("save", 2, 3),  # halfway through writing checkpoint 6: checkpoint 3 stays readable
        ("calibrate", 0, TOTAL),  # the steps are saved; the run calibrates only
    ],
)
def test_a_run_killed_anywhere_resumes_to_the_same_parameters(
    scene, reference, tmp_path, one_thread, monkeypatch, kill, at, resumes_at
):
    run = tmp_path / "run"
    killed_run(scene, run, kill, at)
    assert load_tensors(run / CHECKPOINT)["step"] == resumes_at
    assert (run / LOCK).is_file()  # the killed process's lock file: the OS released its lock
    stray = list(run.glob(".checkpoint.pt.*.tmp"))
    assert bool(stray) == (kill == "save")
    if kill == "calibrate":
        assert not (run / EXTRAPOLATION).exists()
        monkeypatch.setattr(Trainer, "train_step", lambda self: pytest.fail("trained a step again"))
    resumed = Trainer(make_config("tiny", **settings(scene, run)), progress=False)
    assert resumed.state.step == resumes_at
    resumed.train()
    assert not list(run.glob(".checkpoint.pt.*.tmp"))
    assert_same_run(run, reference)


def test_ctrl_c_saves_the_step_reached_and_the_run_resumes_exactly(
    scene, reference, tmp_path, one_thread, monkeypatch
):
    run = tmp_path / "run"
    step = Trainer.train_step

    def interrupted(self):
        if self.state.step == 7:  # the signal comes during step 7: the step ends, then the run stops
            os.kill(os.getpid(), signal.SIGINT)
        return step(self)

    monkeypatch.setattr(Trainer, "train_step", interrupted)
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        train(scene, run)
    assert signal.getsignal(signal.SIGINT) is before  # the handler is put back
    assert load_tensors(run / CHECKPOINT)["step"] == 8
    monkeypatch.undo()
    train(scene, run)
    assert_same_run(run, reference)


@pytest.mark.parametrize("where", ["between steps", "inside a step"])
def test_a_keyboard_interrupt_saves_a_whole_step(scene, reference, tmp_path, one_thread, monkeypatch, where):
    """Raised between two steps, the checkpoint holds the step reached; raised inside one (after its
    optimiser update), the last good state, never half a step."""
    run = tmp_path / "run"
    if where == "between steps":
        step = Trainer.train_step

        def interrupted_before(self):
            if self.state.step == 5:
                raise KeyboardInterrupt
            return step(self)

        monkeypatch.setattr(Trainer, "train_step", interrupted_before)
    else:
        post = trainer_module.DefaultStrategy.step_post_backward

        def interrupted(self, params, optimizers, state, step, info):
            if step == 5:
                raise KeyboardInterrupt
            return post(self, params, optimizers, state, step, info)

        monkeypatch.setattr(trainer_module.DefaultStrategy, "step_post_backward", interrupted)
    with pytest.raises(KeyboardInterrupt):
        train(scene, run)
    assert load_tensors(run / CHECKPOINT)["step"] == (5 if where == "between steps" else 3)
    monkeypatch.undo()
    train(scene, run)
    assert_same_run(run, reference)


def inject_nan(monkeypatch, steps: set[int]) -> list[int]:
    """Make the photometric loss NaN the first time each of ``steps`` is trained; returns the steps hit."""
    loss, hit, trainers = losses_module.photometric_loss, [], []
    step = Trainer.train_step

    def tracking(self):
        trainers[:] = [self]
        return step(self)

    def poisoned(*args, **kwargs):
        losses = loss(*args, **kwargs)
        now = trainers[0].state.step
        if now in steps and now not in hit:
            hit.append(now)
            losses["loss"] = losses["loss"] * float("nan")
        return losses

    monkeypatch.setattr(Trainer, "train_step", tracking)
    monkeypatch.setattr(losses_module, "photometric_loss", poisoned)
    return hit


def test_the_nan_guard_restores_the_last_good_state_with_lower_learning_rates(
    scene, tmp_path, one_thread, monkeypatch
):
    hit = inject_nan(monkeypatch, {5})
    trainer = train(scene, tmp_path / "run")
    assert hit == [5]
    state = trainer.state
    assert state.restorations == [{"step": 5, "to_step": 3, "what": "loss"}]
    assert state.lr_scale == 0.5 and state.step == TOTAL
    optim = trainer.cfg.optim
    assert state.optimizers["quats"].param_groups[0]["lr"] == 0.5 * optim.quat_lr
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())
    steps = [s for s, _ in logged(tmp_path / "run")]
    assert steps == list(range(1, TOTAL + 1))  # the steps after the restored state are logged once
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["nan_restorations"] == state.restorations
    # the lowered rates are part of the checkpoint: a resumed run keeps them
    assert load_tensors(tmp_path / "run" / CHECKPOINT)["lr_scale"] == 0.5


def test_a_parameter_gone_non_finite_is_caught_before_it_is_saved(scene, tmp_path, one_thread, monkeypatch):
    post = trainer_module.DefaultStrategy.step_post_backward
    poisoned = []

    def corrupting(self, params, optimizers, state, step, info):
        report = post(self, params, optimizers, state, step, info)
        if step == 5 and not poisoned:  # after the update of step 5, just before checkpoint 6
            poisoned.append(step)
            params["sh0"].data[0] = float("inf")
        return report

    monkeypatch.setattr(trainer_module.DefaultStrategy, "step_post_backward", corrupting)
    trainer = train(scene, tmp_path / "run")
    assert trainer.state.restorations == [{"step": 6, "to_step": 3, "what": "parameters"}]
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())


def test_a_second_divergence_stops_with_the_last_good_state_saved(scene, tmp_path, one_thread, monkeypatch):
    run = tmp_path / "run"
    inject_nan(monkeypatch, {5, 7})
    with pytest.raises(TrainingDiverged) as err:
        train(scene, run)
    message = str(err.value)
    assert "\n" not in message and str(run) in message
    assert "non-finite loss at step 7" in message and "step 5" in message
    assert load_tensors(run / CHECKPOINT)["step"] == 6  # restored from checkpoint 6 and saved
    assert all(torch.isfinite(v).all() for v in load_tensors(run / CHECKPOINT)["model"].values())


def test_a_second_training_into_a_running_run_folder_is_refused(scene, tmp_path):
    run = tmp_path / "run"
    with lock_run(run):  # as a training in another process holds it
        with pytest.raises(RunError, match=f"{run}: another training \\(pid {os.getpid()} on "):
            train(scene, run)
    assert not (run / CHECKPOINT).exists()
    (run / LOCK).write_text("pid 999999 on elsewhere\n")  # the file of a process long gone: no lock
    assert train(scene, run).state.step == TOTAL


def test_a_run_folder_trained_on_other_images_is_refused_and_a_moved_scene_resumes(scene, tmp_path):
    import shutil

    import imageio.v3 as iio

    run = tmp_path / "run"
    train(scene, run, static_iterations=2, dynamic_iterations=2)
    moved = shutil.copytree(scene, tmp_path / "moved")
    assert (
        Trainer(
            make_config("tiny", **settings(moved, run, static_iterations=2, dynamic_iterations=2))
        ).state.step
        == 4
    )
    image = moved / "train" / "c0_f0.png"
    pixels = iio.imread(image)
    pixels[12, 12, :3] = 255 - pixels[12, 12, :3]
    iio.imwrite(image, pixels)
    with pytest.raises(RunError, match=f"trained on other images \\({scene}\\) than those of --data {moved}"):
        Trainer(make_config("tiny", **settings(moved, run, static_iterations=2, dynamic_iterations=2)))


def test_first_non_finite_finds_nan_and_inf_and_passes_empty_tensors():
    from tracegs.train.guard import first_non_finite

    finite, empty = torch.tensor([1.0, -3e38]), torch.zeros(0, 3)
    assert first_non_finite([finite, empty, finite.bfloat16()]) is None
    assert first_non_finite([]) is None
    for bad in (float("nan"), float("inf"), -float("inf")):
        assert first_non_finite([finite, empty, torch.tensor([[0.0, bad]])]) == 2


def test_any_non_finite_sees_every_nan_and_inf_and_changes_nothing():
    from tracegs.train.guard import NonFinite, any_non_finite, check_step

    finite = [torch.tensor([1.0, -3e38, 2.5e-38]), torch.zeros(0, 3), torch.randn(64, 64)]
    copies = [t.clone() for t in finite]
    assert not any_non_finite(finite) and not any_non_finite([])
    assert all(torch.equal(a, b) for a, b in zip(finite, copies, strict=True))  # the check writes nothing
    for bad in (float("nan"), float("inf"), -float("inf")):
        for index in range(3):
            tensors = [t.clone() for t in finite]
            tensors[index] = torch.tensor([[0.0, bad]]) if index == 1 else tensors[index]
            if index != 1:
                tensors[index].view(-1)[-1] = bad
            assert any_non_finite(tensors)
            assert any_non_finite([t.bfloat16() for t in tensors])  # (the fallback's dtype)
    params = [torch.nn.Parameter(torch.ones(3))]
    params[0].grad = torch.tensor([0.0, float("nan"), 1.0])
    with pytest.raises(NonFinite, match="gradient"):
        check_step(torch.tensor(0.5), params, 7)
    with pytest.raises(NonFinite, match="loss"):
        check_step(torch.tensor(float("inf")), params, 7)


def test_the_progress_bar_shows_the_stage_loss_and_gaussians(scene, tmp_path, capsys):
    cfg = make_config("tiny", **settings(scene, tmp_path / "run", static_iterations=2, dynamic_iterations=2))
    Trainer(cfg, progress=True).train()
    err = capsys.readouterr().err
    assert "train stage 2 (trace)" in err and "4/4" in err
    assert (
        "loss=" in err
        and f"gaussians={load_tensors(tmp_path / 'run' / CHECKPOINT)['model']['gaussians.means'].shape[0]}"
        in err
    )
