"""tests/setup-and-run.sh (README's test command, .ci/run's main run) installs only what is missing, and npm only
when Node.js did not bring it: the script runs for real against stand-ins for apt-get, npm and Python that log
their arguments and "install" what a Debian or a NodeSource package would put on the PATH."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "setup-and-run.sh"
BASH = shutil.which("bash") or "/bin/bash"
MKDIR, TOUCH = shutil.which("mkdir") or "/bin/mkdir", shutil.which("touch") or "/usr/bin/touch"


class Machine:
    """A PATH of stand-ins (nothing else on it) and the log of what was run; ``has`` the programs installed."""

    def __init__(self, tmp: Path, has: tuple[str, ...], apt: str) -> None:
        self.bin = tmp / "bin"
        self.bin.mkdir()
        self.log = tmp / "log"
        self.log.write_text("")
        self.venv = tmp / "venv"
        for name in has:
            self.program(name)
        # apt-get: `apt` says what installing a package puts on the PATH ("nodejs=node,npm"); "stale" fails every
        # install until `apt-get update`; a package missing from `apt` cannot be installed (a conflict).
        packages = dict(entry.split("=") for entry in apt.split(";") if entry and entry != "stale")
        cases = "\n".join(f'        {pkg}) for p in {" ".join(progs.split(","))}; do make "$p"; done ;;'
                          for pkg, progs in packages.items())
        self.program("apt-get", f'''
make() {{ printf '#!{BASH}\\necho "%s $*" >> "{self.log}"\\n' "$1" > "{self.bin}/$1"; /bin/chmod +x "{self.bin}/$1"; }}
[[ "$1" == update ]] && {{ {TOUCH} "{tmp}/updated"; exit 0; }}
{"[[ -e " + str(tmp) + "/updated ]] || exit 100" if "stale" in apt else ""}
shift 3  # install -y -q
for pkg in "$@"; do
    case "$pkg" in
{cases}
        *) exit 100 ;;
    esac
done''')
        self.program("python3", f'''
[[ "$1 $2" == "-m venv" ]] || exit 1
{MKDIR} -p "$3/bin"
for tool in pip python; do
    printf '#!{BASH}\\necho "%s $*" >> "{self.log}"\\n[[ "$2" == pytest ]] && exit 3\\nexit 0\\n' "$tool" > "$3/bin/$tool"
    /bin/chmod +x "$3/bin/$tool"
done''')

    def program(self, name: str, body: str = "") -> None:
        path = self.bin / name
        path.write_text(f'#!{BASH}\necho "{name} $*" >> "{self.log}"\n{body}\n')
        path.chmod(0o755)

    def run(self, *args: str) -> subprocess.CompletedProcess[str]:
        env = {"PATH": str(self.bin), "VENV": str(self.venv), "AUTOTUNER_PG_BIN": "/nonexistent",
               "HOME": os.environ.get("HOME", "/root")}
        return subprocess.run([BASH, str(SCRIPT), *args], capture_output=True, text=True, env=env, timeout=60)

    def ran(self) -> list[str]:
        return self.log.read_text().splitlines()


def _after_apt(venv: Path, pytest_args: str = "-n 2 -q") -> list[str]:
    return ["npm ci --prefix tests/opcua_node --no-audit --no-fund --loglevel=error", f"python3 -m venv {venv}",
            "pip install --quiet -e .[test]", f"python -m pytest {pytest_args}"]


@pytest.fixture(autouse=True)
def _posix_tools():
    if not (os.access("/bin/chmod", os.X_OK) and Path(BASH).exists()):
        pytest.fail("these tests need bash and /bin/chmod", pytrace=False)


def test_plain_debian_gets_nodejs_then_npm_separately(tmp_path):
    machine = Machine(tmp_path, has=(), apt="chromium=chromium;nodejs=node;npm=npm")
    done = machine.run()
    assert done.returncode == 3, done.stderr  # pytest's exit code (the stand-in's pytest exits 3)
    assert machine.ran() == ["apt-get install -y -q chromium nodejs", "apt-get install -y -q npm",
                             *_after_apt(machine.venv)]


def test_a_nodejs_that_carries_npm_never_gets_debians_npm(tmp_path):
    # NodeSource's nodejs brings npm; Debian's npm conflicts with it (apt has no installable npm here).
    machine = Machine(tmp_path, has=("chromium",), apt="nodejs=node,npm")
    done = machine.run("-k", "modbus")
    assert done.returncode == 3, done.stderr
    assert machine.ran() == ["apt-get install -y -q nodejs", *_after_apt(machine.venv, "-k modbus")]


def test_nothing_missing_installs_nothing(tmp_path):
    machine = Machine(tmp_path, has=("chromium", "node", "npm"), apt="")
    machine.run()
    assert machine.ran() == _after_apt(machine.venv)


def test_stale_package_lists_are_updated_once_and_the_install_retried(tmp_path):
    machine = Machine(tmp_path, has=("node", "npm"), apt="stale;chromium=chromium")
    machine.run()
    assert machine.ran()[:3] == ["apt-get install -y -q chromium", "apt-get update -q",
                                 "apt-get install -y -q chromium"]


def test_node_without_npm_that_apt_cannot_add_is_a_clear_error(tmp_path):
    machine = Machine(tmp_path, has=("chromium", "node"), apt="")
    done = machine.run()
    assert done.returncode == 2
    assert "node is installed but npm is not" in done.stderr
    assert not any(line.startswith(("npm", "python")) for line in machine.ran())  # nothing ran after


def test_an_existing_venv_is_kept_and_dry_run_runs_nothing(tmp_path):
    machine = Machine(tmp_path, has=("chromium", "node", "npm"), apt="")
    machine.run()  # creates the venv
    machine.log.write_text("")
    done = subprocess.run([BASH, str(SCRIPT)], capture_output=True, text=True, timeout=60,
                          env={"PATH": str(machine.bin), "VENV": str(machine.venv), "AUTOTUNER_PG_BIN": "/x",
                               "DRY_RUN": "1"})
    assert done.returncode == 0, done.stderr
    assert machine.ran() == []  # nothing was run...
    assert done.stdout.splitlines() == [  # ...only printed, and the venv made by the first run is kept
        "+ npm ci --prefix tests/opcua_node --no-audit --no-fund --loglevel=error",
        f"+ {machine.venv}/bin/pip install --quiet -e .[test]", f"+ {machine.venv}/bin/python -m pytest -n 2 -q"]


def test_dry_run_on_plain_debian_prints_nodejs_then_npm(tmp_path):
    machine = Machine(tmp_path, has=(), apt="")
    done = subprocess.run([BASH, str(SCRIPT), "tests/test_pid.py"], capture_output=True, text=True, timeout=60,
                          env={"PATH": str(machine.bin), "VENV": str(machine.venv), "AUTOTUNER_PG_BIN": "/x",
                               "DRY_RUN": "1"})
    assert done.returncode == 0, done.stderr
    assert machine.ran() == []
    assert done.stdout.splitlines()[:2] == ["+ apt-get install -y -q chromium nodejs", "+ apt-get install -y -q npm"]
    assert done.stdout.splitlines()[-1] == f"+ {machine.venv}/bin/python -m pytest tests/test_pid.py"
