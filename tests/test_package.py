import subprocess
import sys

import pytest

#: importing the package and its command line, maps and recordings loads none of the extras
_PACKAGE = (
    "flyvpr, flyvpr.cli, flyvpr.localization, flyvpr.evaluation, flyvpr.localization.maps, "
    + ("flyvpr.sources, flyvpr.localization.tracking, flyvpr.localization.trace")
)


@pytest.mark.parametrize("extras", [("torch", "matplotlib"), ("av", "rosbags"), ("numba",)])
def test_import_loads_no_optional_dependency(extras):
    code = (
        f"import sys, {_PACKAGE}; bad = [m for m in {extras!r} if m in sys.modules]; "
        "print(','.join(bad)); sys.exit(1 if bad else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert res.returncode == 0, f"imported: {res.stdout} {res.stderr}"


def test_version_is_written_once():
    from pathlib import Path

    import tomllib

    import flyvpr
    from flyvpr._version import __version__

    assert flyvpr.__version__ is __version__ and __version__.count(".") == 2
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert pyproject["tool"]["setuptools"]["dynamic"]["version"] == {
        "attr": "flyvpr._version.__version__"
    }
    assert "version" not in pyproject["project"]
