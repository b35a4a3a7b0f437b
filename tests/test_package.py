import subprocess
import sys


def test_import_loads_neither_torch_nor_matplotlib():
    code = (
        "import sys, flyvpr, flyvpr.cli, flyvpr.localizer, flyvpr.evaluation;"
        "bad = [m for m in ('torch', 'matplotlib') if m in sys.modules];"
        "print(','.join(bad)); sys.exit(1 if bad else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert res.returncode == 0, f"imported: {res.stdout} {res.stderr}"


def test_version():
    import flyvpr

    assert flyvpr.__version__
