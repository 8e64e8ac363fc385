import subprocess
import sys


def run(*args):
    return subprocess.run([sys.executable, "-m", "blockloc.cli", *args], capture_output=True, text=True)


def test_help_and_version():
    out = run("--help")
    assert out.returncode == 0 and "eval" in out.stdout
    out = run("--version")
    assert out.returncode == 0 and out.stdout.startswith("blockloc ")


def test_cli_import_stays_light():
    code = ("import sys, blockloc.cli; heavy = [m for m in ('gtsam', 'open3d', 'numba', 'matplotlib', "
            "'small_gicp', 'rosbags', 'scipy', 'cyclonedds') if m in sys.modules]; print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_unknown_command_fails_without_traceback():
    out = run("no-such-command")
    assert out.returncode != 0
    assert "Traceback" not in out.stderr
