"""The CI scripts on a bare machine, without touching this one.

`.ci/install`, `.ci/runtime-only`, `.ci/browser` and `.ci/run` run with a PATH of stubs: `apt-get`, `sudo`,
`ldconfig`, `ls`, `id`, `python` and the commands the scripts call record their arguments (and the environment
variables apt-get and the test run need); everything else on that PATH is a link to the real tool.
`glslangValidator`, `shellcheck`, `espeak-ng`, `festival`, `flite`, `nginx`, `chromium` and `npm` are missing,
`ldconfig` lists no libEGL and `ls` finds no DRI driver (nor festival's voices), so the install must ask apt-get for
every Debian package, as root and through sudo as another user.
Where `.ci/browser` fails, `.ci/run` must still run the suite with CI set and then fail; and the browser tests
themselves, run in a fresh pytest without chromium (or without the npm renderer), must fail with CI set and skip
without it. shellcheck lints every script in `.ci/` (CI installs it; elsewhere that test skips).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree

import pytest
from ci_tools import BROWSER_INSTALL, need

ROOT = Path(__file__).resolve().parent.parent
CI_DIR = ROOT / ".ci"
# Real tools the scripts use besides the stubbed ones (bash builtins need none).
REAL_TOOLS = ("bash", "env", "grep", "dirname", "cat", "mktemp", "rm", "wc", "test", "mkdir", "touch", "true")
DEBIAN_PACKAGES = {"libegl1", "libgl1-mesa-dri", "glslang-tools", "shellcheck", "espeak-ng", "nginx", "festival",
                   "festvox-us-slt-hts", "festvox-kallpc16k", "festvox-kdlpc16k", "flite", "festvox-italp16k",
                   "festvox-itapc16k", "festvox-czech-dita", "festvox-czech-krb", "festvox-czech-machac",
                   "festvox-czech-ph", "festvox-suopuhe-lj", "festvox-suopuhe-mv", "festvox-ca-ona-hts"}

# Each stub appends one line to $STUB_LOG: its name, then its arguments separated by tabs. The line goes out in one
# write (an O_APPEND write is atomic), because .ci/run runs .ci/browser beside .ci/runtime-only and their stubs'
# lines would otherwise interleave.
RECORD = 'printf -v stub_args "\\t%s" "$@"; printf "%s%s\\n" "$(basename "$0")" "$stub_args" >>"$STUB_LOG"\n'
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
  "-m pytest") echo "pytest-ci	${CI-unset}" >>"$STUB_LOG" ;;  # the test run: is CI set for it?
  "-m venv") mkdir -p "$3/bin"
             for tool in python gt-export gt-bench gt-serve; do ln -s "$STUB_DIR/$tool" "$3/bin/$tool"; done ;;
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
    # gt-bench: `lam-web --install` (.ci/browser's npm install) exits $STUB_NPM_RC; the rest refuses as without torch.
    "gt-bench": RECORD + """[ "$1" = lam-web ] && exit "${STUB_NPM_RC:-0}"
echo "gt-bench: needs the 'export' extra (torch not installed): pip install ..." >&2
exit 2
""",
    # gt-serve in a runtime-only venv: no `serve` extra, one line.
    "gt-serve": RECORD + """echo "gt-serve: needs the 'serve' extra (aiohttp not installed): ..." >&2
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
    assert ".[export,dev,mnn,serve,pipecat,cpu,ray,voice]" in pips[1]
    assert any("opencv-python-headless" in arg for arg in pips[2])
    # the real recordings of the lip-sync measurement come at install, from the packages that ship them
    assert ["python", "-m", "gaussiantalker.exporter.voice.real_speech", "fetch"] in calls


def test_install_asks_apt_for_nothing_when_everything_is_there(tmp_path):
    env, log = _stub_path(tmp_path, 0)
    bin_dir = Path(env["PATH"])
    for tool in ("glslangValidator", "shellcheck", "espeak-ng", "nginx", "festival", "flite"):
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
    assert commands.count("gt-serve") == 1, calls
    assert any(call[0] == "python" and "samples/play.py" in call for call in calls)


def test_runtime_only_fails_when_the_virtualenv_has_torch(tmp_path):
    env, log = _stub_path(tmp_path, 0)
    python = Path(env["PATH"]) / "python"
    python.write_text(python.read_text().replace('"-c import cv2"|"-c import torch"', '"-c import cv2"'))
    result = _run("runtime-only", env)
    assert result.returncode == 1 and "torch is importable" in result.stderr


@pytest.mark.parametrize("uid", [0, 1000], ids=["root", "sudo-user"])
def test_browser_installs_chromium_and_the_npm_renderer(tmp_path, uid):
    env, log = _stub_path(tmp_path, uid)
    result = _run("browser", env)
    assert result.returncode == 0, result.stdout + result.stderr
    calls = _calls(log)
    apt = [call for call in calls if call[0] == "apt-get"]
    assert [call[1] for call in apt] == ["update", "install"] and {"chromium", "npm"} <= set(apt[1]), calls
    assert ["gt-bench", "lam-web", "--install"] in calls, calls
    assert ["python", "-m", "tools.browser.web_cli", "install"] in calls  # from the checkout's root
    assert len([call for call in calls if call[0] == "sudo"]) == (0 if uid == 0 else 2), calls
    env["STUB_NPM_RC"] = "1"  # the npm renderer cannot be installed (no registry, a broken package)
    assert _run("browser", env).returncode != 0


@pytest.mark.parametrize("npm_rc", [0, 1], ids=["browser-ok", "browser-fails"])
def test_run_sets_ci_for_the_suite_and_fails_where_the_browser_tools_did(tmp_path, npm_rc):
    """.ci/run on a bare machine: install, browser tools, runtime-only, then the suite with CI set (so tests that
    need a CI-installed tool fail instead of skipping). Where .ci/browser fails, the suite still runs (the browser
    tests fail in it: test_browser_tests_fail_under_ci_without_their_tools) and .ci/run fails."""
    env, log = _stub_path(tmp_path, 0)
    env["STUB_NPM_RC"] = str(npm_rc)
    result = subprocess.run(["bash", str(CI_DIR / "run")], env=env, capture_output=True, text=True, timeout=120,
                            executable=shutil.which("bash"))
    calls = _calls(log)
    assert ["python", "-m", "pytest", "-q"] in calls and ["pytest-ci", "true"] in calls, calls
    assert ["gt-bench", "lam-web", "--install"] in calls, calls
    if npm_rc == 0:
        assert result.returncode == 0, result.stdout + result.stderr
        assert "could not be installed" not in result.stderr
    else:
        assert result.returncode == 1, result.stdout + result.stderr
        assert "the browser tests (tests/test_lam_web.py, tests/test_live_browser.py, tests/test_web_player.py) " \
            "fail" in result.stderr


# Loaded into the fresh pytest below (-p): Chromium's fixed path becomes $STUB_CHROMIUM, missing or a stub.
STUB_BROWSER_PLUGIN = """\
import os
from tools.browser import chromium
chromium.CHROMIUM = os.environ["STUB_CHROMIUM"]
"""
BROWSER_MODULES = ("tests/test_lam_web.py", "tests/test_live_browser.py", "tests/test_web_player.py")
# Browser tests that need only chromium, and some that need the npm renderer as well.
NEEDS_CHROMIUM = {"test_headless_chromium_has_webgl2_with_our_flags",
                  "test_browser_receives_the_head_talking_with_its_microphone",
                  "test_a_page_that_leaves_mid_reply_ends_its_session", "test_a_wrong_magic_is_refused",
                  "test_sample_page_plays_a_bundle_with_its_audio"}
NEEDS_RENDERER = {"test_harness_page_imports_the_installed_renderer", "test_cli_writes_frames_cameras_and_weights",
                  "test_runtime_frames_match_the_web_renderer", "test_synthetic_background_is_the_clear_colour",
                  "test_synthetic_splats_land_where_our_camera_projects_them"}
# Skips that stay under CI: opt-ins, not tools CI installs.
OPT_IN_SKIPS = ("GT_LAM_AVATAR", "GT_HEAVY")


def _browser_outcomes(tmp_path: Path, ci: bool, chromium: bool, *args: str) -> dict[str, tuple[str, str]]:
    """Run the browser test modules in a fresh pytest, chromium missing (or a stub that is never started) and the
    npm renderer's cache empty: {test name: (passed | failed | error | skipped, message)}."""
    plugin_dir = tmp_path / "plugin"
    plugin_dir.mkdir()
    (plugin_dir / "stub_browser.py").write_text(STUB_BROWSER_PLUGIN)
    stub = tmp_path / "chromium"
    if chromium:
        stub.write_text("#!/bin/sh\nexit 1\n")
        stub.chmod(0o755)
    env = {key: value for key, value in os.environ.items()
           if key not in ("CI", "GT_HEAVY", "GT_LAM_AVATAR", "PYTEST_ADDOPTS")}
    env.update(STUB_CHROMIUM=str(stub), GT_LAM_WEB_CACHE=str(tmp_path / "empty-npm-cache"),
               PYTHONPATH=os.pathsep.join(filter(None, [str(plugin_dir), os.environ.get("PYTHONPATH")])))
    if ci:
        env["CI"] = "true"
    report = tmp_path / "report.xml"
    result = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "stub_browser",
                             "-o", "addopts=", f"--junitxml={report}", *args, *BROWSER_MODULES], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=300)
    assert report.exists(), result.stdout[-3000:] + result.stderr[-3000:]
    outcomes = {}
    for case in ElementTree.parse(report).getroot().iter("testcase"):
        name = case.get("name").split("[")[0]
        results = [child for child in case if child.tag in ("failure", "error", "skipped")]
        outcome = (results[-1].tag, results[-1].get("message", "")) if results else ("passed", "")
        if outcomes.get(name, ("passed",))[0] == "passed":  # parametrized: the first non-pass stands for all
            outcomes[name] = outcome
    return outcomes


@pytest.mark.parametrize("ci", [True, False], ids=["CI", "no-CI"])
def test_browser_tests_fail_under_ci_without_chromium(tmp_path, ci):
    """Without chromium every browser test fails where CI is set (naming it and .ci/browser), and skips
    elsewhere; the tests that need no browser pass either way, and only opt-in tests skip under CI."""
    outcomes = _browser_outcomes(tmp_path, ci, chromium=False)
    browser = {name: outcome for name, outcome in outcomes.items() if "Chromium not found" in outcome[1]}
    assert NEEDS_CHROMIUM | NEEDS_RENDERER <= set(browser), sorted(outcomes)
    for name, (kind, message) in browser.items():
        assert kind in (("failure", "error") if ci else ("skipped",)), (name, kind, message)
        assert (BROWSER_INSTALL in message) == ci, (name, message)
    others = {name: outcome for name, outcome in outcomes.items() if name not in browser}
    assert {kind for kind, _ in others.values()} <= {"passed", "skipped"}, others
    assert all(any(opt_in in message for opt_in in OPT_IN_SKIPS) for kind, message in others.values()
               if kind == "skipped"), others
    assert sum(kind == "passed" for kind, _ in others.values()) >= 10, others  # the camera maths, the CLI...


def test_browser_tests_fail_under_ci_without_the_npm_renderer(tmp_path):
    """Chromium there but the npm renderer not (`npm install` failed): the renderer's tests fail where CI is set,
    naming the npm package and .ci/browser (without CI they skip through the same helper as above)."""
    outcomes = _browser_outcomes(tmp_path, True, True, "-k", " or ".join(sorted(NEEDS_RENDERER)))
    assert set(outcomes) == NEEDS_RENDERER, sorted(outcomes)
    for name, (kind, message) in outcomes.items():
        assert kind in ("failure", "error"), (name, kind, message)
        assert "gaussian-splat-renderer-for-lam" in message and BROWSER_INSTALL in message, (name, message)


def test_ci_scripts_pass_shellcheck():
    shellcheck = shutil.which("shellcheck")
    need(None if shellcheck else "shellcheck is not installed (Debian: apt-get install shellcheck)",
         ".ci/install (Debian package shellcheck)")
    scripts = sorted(str(path) for path in CI_DIR.iterdir() if path.is_file())
    result = subprocess.run([shellcheck, "--shell=bash", *scripts], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout
