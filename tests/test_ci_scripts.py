"""The CI scripts on a bare machine, without touching this one.

`.ci/install` and `.ci/runtime-only` run with a PATH of stubs: `apt-get`, `sudo`, `ldconfig`, `ls`, `id`, `python`
and the commands `.ci/runtime-only` calls record their arguments (and the environment variable apt-get needs);
everything else on that PATH is a link to the real tool. `glslangValidator` and `shellcheck` are missing, `ldconfig`
lists no libEGL and `ls` finds no DRI driver, so the install must ask apt-get for every Debian package, as root
and through sudo as another user. shellcheck lints every script in `.ci/` (CI installs it; elsewhere that test
skips).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CI_DIR = ROOT / ".ci"
# Real tools the scripts use besides the stubbed ones (bash builtins need none).
REAL_TOOLS = ("bash", "env", "grep", "dirname", "cat", "mktemp", "rm", "wc", "test", "mkdir", "touch", "true")
DEBIAN_PACKAGES = {"libegl1", "libgl1-mesa-dri", "glslang-tools", "shellcheck"}

# Each stub appends one line to $STUB_LOG: its name, then its arguments separated by tabs.
RECORD = 'printf "%s" "$(basename "$0")" >>"$STUB_LOG"; printf "\\t%s" "$@" >>"$STUB_LOG"; echo >>"$STUB_LOG"\n'
STUBS = {
    # apt-get also records whether it would ask questions (DEBIAN_FRONTEND must reach it as noninteractive).
    "apt-get": RECORD + 'echo "apt-get-frontend\t${DEBIAN_FRONTEND:-unset}" >>"$STUB_LOG"\n',
    # sudo runs the rest as given; `sudo VAR=value cmd` sets VAR as the real sudo does.
    "sudo": RECORD + 'exec env "$@"\n',
    "ldconfig": RECORD + 'echo "1 libs found in cache"\n',  # no libEGL.so.1
    "ls": RECORD + "exit 2\n",  # no /usr/lib/*/dri/swrast_dri.so
    "id": RECORD + 'echo "$STUB_UID"\n',
    # python: `-c "import cv2"` fails (so OpenCV is installed), `-m venv DIR` makes DIR/bin with these stubs,
    # `-c "import torch"` fails, like a runtime-only virtualenv should; an `-o FILE` argument creates FILE.
    "python": RECORD + """\
case "$1 $2" in
  "-c import cv2"|"-c import torch") exit 1 ;;
  "-m venv") mkdir -p "$3/bin"
             for tool in python gt-export gt-bench; do ln -s "$STUB_DIR/$tool" "$3/bin/$tool"; done ;;
esac
while [ $# -gt 0 ]; do [ "$1" = "-o" ] && echo stub >"$2"; shift; done  # scripts' outputs exist afterwards
exit 0
""",
    # the exporter commands: gt-export writes its -o file; in a runtime-only venv both refuse with the one line.
    "gt-export": RECORD + """\
case "$0" in
  */venv/bin/*) echo "gt-export: needs the 'export' extra (torch not installed): pip install ..." >&2; exit 2 ;;
esac
while [ $# -gt 0 ]; do [ "$1" = "-o" ] && echo stub >"$2"; shift; done
""",
    "gt-bench": RECORD + """echo "gt-bench: needs the 'export' extra (torch not installed): pip install ..." >&2
exit 2
""",
}


def _stub_path(tmp_path: Path, uid: int) -> tuple[dict, Path]:
    """Environment whose PATH holds only the stubs and links to the real tools; and the stub log."""
    stub_dir = tmp_path / "bin"
    stub_dir.mkdir()
    for name, body in STUBS.items():
        stub = stub_dir / name
        stub.write_text("#!/bin/bash\n" + body)
        stub.chmod(0o755)
    for tool in REAL_TOOLS + ("basename", "printf", "ln"):
        real = shutil.which(tool)
        if real is not None and not (stub_dir / tool).exists():
            (stub_dir / tool).symlink_to(real)
    log = tmp_path / "calls.log"
    log.touch()
    env = {"PATH": str(stub_dir), "HOME": str(tmp_path), "STUB_LOG": str(log), "STUB_DIR": str(stub_dir),
           "STUB_UID": str(uid), "TMPDIR": str(tmp_path)}
    return env, log


def _run(script: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(CI_DIR / script)], env=env, capture_output=True, text=True, timeout=60,
                          executable=shutil.which("bash"))


def _calls(log: Path) -> list[list[str]]:
    return [line.split("\t") for line in log.read_text().splitlines()]


@pytest.mark.parametrize("uid", [0, 1000], ids=["root", "sudo-user"])
def test_install_asks_apt_for_every_missing_package(tmp_path, uid):
    env, log = _stub_path(tmp_path, uid)
    assert shutil.which("glslangValidator", path=env["PATH"]) is None
    result = _run("install", env)
    assert result.returncode == 0, result.stderr
    calls = _calls(log)
    apt = [call for call in calls if call[0] == "apt-get"]
    assert [call[1] for call in apt] == ["update", "install"], calls
    assert set(apt[1][2:]) - {"-y", "-qq"} == DEBIAN_PACKAGES
    assert ["apt-get-frontend", "noninteractive"] in calls, "apt-get install would ask questions"
    sudo = [call for call in calls if call[0] == "sudo"]
    # root runs apt-get itself; another user goes through sudo for both apt-get calls
    assert len(sudo) == (0 if uid == 0 else 2), calls
    pips = [call for call in calls if call[0] == "python" and call[1:4] == ["-m", "pip", "install"]]
    assert ["torch==2.13.0"] == [arg for arg in pips[0] if arg.startswith("torch")], "torch (CPU) comes first"
    assert ".[export,dev,mnn,live,pipecat,cpu]" in pips[1]
    assert any("opencv-python-headless" in arg for arg in pips[2])


def test_install_asks_apt_for_nothing_when_everything_is_there(tmp_path):
    env, log = _stub_path(tmp_path, 0)
    bin_dir = Path(env["PATH"])
    for tool in ("glslangValidator", "shellcheck"):
        (bin_dir / tool).symlink_to(bin_dir / "true")
    (bin_dir / "ldconfig").write_text('#!/bin/bash\necho "libEGL.so.1 (libc6,x86-64) => /lib/libEGL.so.1"\n')
    (bin_dir / "ls").write_text("#!/bin/bash\necho /usr/lib/x86_64-linux-gnu/dri/swrast_dri.so\n")
    result = _run("install", env)
    assert result.returncode == 0, result.stderr
    assert not [call for call in _calls(log) if call[0] in ("apt-get", "sudo")]


@pytest.mark.parametrize("uid", [0, 1000], ids=["root", "sudo-user"])
def test_runtime_only_runs_on_a_bare_machine(tmp_path, uid):
    """It needs no Debian package and no sudo: only python, a virtualenv and the exporter's commands."""
    env, log = _stub_path(tmp_path, uid)
    result = _run("runtime-only", env)
    assert result.returncode == 0, result.stdout + result.stderr
    calls = _calls(log)
    assert not [call for call in calls if call[0] in ("apt-get", "sudo")]
    commands = [call[0] for call in calls]
    assert commands.count("gt-export") == 2 and commands.count("gt-bench") == 1, calls  # export + two refusals
    assert any(call[0] == "python" and "samples/play.py" in call for call in calls)


def test_runtime_only_fails_when_the_virtualenv_has_torch(tmp_path):
    env, log = _stub_path(tmp_path, 0)
    python = Path(env["PATH"]) / "python"
    python.write_text(python.read_text().replace('"-c import cv2"|"-c import torch"', '"-c import cv2"'))
    result = _run("runtime-only", env)
    assert result.returncode == 1 and "torch is importable" in result.stderr


def test_ci_scripts_pass_shellcheck():
    shellcheck = shutil.which("shellcheck")
    if shellcheck is None:
        if os.environ.get("CI"):
            pytest.fail("shellcheck is not on PATH but CI is set: .ci/install installs it (Debian package shellcheck)")
        pytest.skip("shellcheck not installed (Debian: apt-get install shellcheck); CI requires it")
    scripts = sorted(str(path) for path in CI_DIR.iterdir() if path.is_file())
    result = subprocess.run([shellcheck, "--shell=bash", *scripts], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout
