import subprocess
import sys

import pytest

#: importing the package and its command line, maps and recordings loads none of the extras
_PACKAGE = "flyvpr, flyvpr.cli, flyvpr.localizer, flyvpr.evaluation, flyvpr.maps, " + (
    "flyvpr.sources, flyvpr.tracking, flyvpr.trace"
)


@pytest.mark.parametrize("extras", [("torch", "matplotlib"), ("av", "rosbags")])
def test_import_loads_no_optional_dependency(extras):
    code = (
        f"import sys, {_PACKAGE}; bad = [m for m in {extras!r} if m in sys.modules]; "
        "print(','.join(bad)); sys.exit(1 if bad else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert res.returncode == 0, f"imported: {res.stdout} {res.stderr}"


def test_version():
    import flyvpr

    assert flyvpr.__version__
