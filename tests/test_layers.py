"""The shape of the package: the import-linter contract of pyproject.toml (layers, no cycles between
packages), files a reader can take in, every declared dependency used, ``python -m tracegs``."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "tracegs"


def test_the_import_contracts_hold():
    lint = Path(sys.executable).parent / "lint-imports"
    if not lint.is_file():
        pytest.skip("import-linter is not installed (bash scripts/install.sh test)")
    out = subprocess.run([str(lint)], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "0 broken" in out.stdout


def test_the_layer_contract_names_every_package():
    """A new package joins a layer (else import-linter would not check it)."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    layers = next(c for c in config["contracts"] if c["type"] == "layers")["layers"]
    named = {name.strip() for layer in layers for name in layer.split("|")}
    present = {
        f"tracegs.{p.stem}"
        for p in SRC.iterdir()
        if p.suffix == ".py" and p.stem not in ("__init__", "__main__")
    }
    present |= {f"tracegs.{p.name}" for p in SRC.iterdir() if (p / "__init__.py").is_file()}
    assert present == named


def test_no_python_file_is_longer_than_400_lines():
    long = {
        str(p.relative_to(SRC)): n for p in SRC.rglob("*.py") if (n := len(p.read_text().splitlines())) > 400
    }
    assert not long


def _imported_top_level_modules() -> set[str]:
    names = set()
    for path in SRC.rglob("*.py"):
        for line in path.read_text().splitlines():
            m = re.match(r"\s*(?:from|import)\s+([A-Za-z_][A-Za-z0-9_]*)", line)
            if m:
                names.add(m.group(1))
    return names


# distribution name -> the module it is imported as
MODULE = {"pytorch-msssim": "pytorch_msssim", "imageio-ffmpeg": "imageio_ffmpeg", "scikit-learn": "sklearn"}


def test_every_declared_dependency_is_imported():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    names = [re.split(r"[<>=!~ \[]", d, maxsplit=1)[0] for d in deps]
    imported = _imported_top_level_modules()
    unused = [n for n in names if MODULE.get(n, n.replace("-", "_")) not in imported]
    assert not unused


def test_python_dash_m_tracegs_runs_the_cli():
    out = subprocess.run([sys.executable, "-m", "tracegs", "--help"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "usage: tracegs" in out.stdout and "calibrate" in out.stdout


def _reach_ins(pattern: str, allowed: Path, root: Path = SRC) -> list[str]:
    """``path:line`` of the lines of the package ``root`` outside ``allowed`` (a file or a folder) that
    match ``pattern``, comments and docstrings included (a reach-in only mentioned is still one)."""
    found = []
    for path in root.rglob("*.py"):
        if path == allowed or allowed in path.parents:
            continue
        for i, line in enumerate(path.read_text().splitlines(), start=1):
            if re.search(pattern, line):
                found.append(f"{path.relative_to(root)}:{i}")
    return found


def test_no_code_reaches_into_a_models_config_or_the_trainer():
    """Settings reach a module as its own sections (a trained run's through ``extrapolate.Predictor``),
    and the trainer's state is its own (``train/state.py``): nothing outside ``models/`` reads
    ``model.cfg``, nothing outside ``train/trainer.py`` reads ``trainer.<attribute>``."""
    assert not _reach_ins(r"\bmodel\.cfg\b", SRC / "models")
    assert not _reach_ins(r"\btrainer\.[a-z_]", SRC / "train" / "trainer.py")


def test_the_reach_in_check_finds_a_reach_in(tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "trace.py").write_text("self.cfg = cfg\nsh = model.cfg.sh_degree\n")
    (tmp_path / "eval.py").write_text("a = predictor.model.cfgs\nb = model.cfg.extrapolation\n")
    assert _reach_ins(r"\bmodel\.cfg\b", tmp_path / "models", tmp_path) == ["eval.py:2"]
