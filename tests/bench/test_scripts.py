"""The benchmark shell scripts run the modules they name (they run on machines CI never sees)."""

import importlib.util
import re
from pathlib import Path

import pytest

SCRIPTS = sorted((Path(__file__).parents[2] / "benchmarks").glob("*.sh"))


@pytest.mark.parametrize("script", SCRIPTS, ids=[s.name for s in SCRIPTS])
def test_every_python_dash_m_of_a_script_is_runnable(script):
    modules = re.findall(r"\s-m\s+([A-Za-z_][\w.]*)", script.read_text())
    assert modules, f"{script.name} names no module"
    for name in modules:
        spec = importlib.util.find_spec(name)
        assert spec is not None, f"{script.name}: no module {name}"
        if spec.submodule_search_locations is not None:  # a package runs through its __main__
            assert importlib.util.find_spec(name + ".__main__") is not None, (
                f"{script.name}: {name} has no __main__"
            )
