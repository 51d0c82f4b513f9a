"""web/ as the npm package an app installs (web/README.md, docs/web.md "The npm package"): `npm pack` makes a
tarball holding the player's modules, its TypeScript declarations and README and nothing of the repository's
harness; a scratch app installs it offline (its dependencies from the npm cache `npm ci` in web/ filled), compiles
against its declarations with `tsc --strict`, and a page of that app plays a bundle in headless chromium within 3
levels of the Python runtime's frames, importing the package by name as the repository's own pages do."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest
from ci_tools import BROWSER_INSTALL, need, need_chromium

from gaussiantalker.sdk.image import psnr_db

ROOT = Path(__file__).resolve().parents[1]
WEB = ROOT / "web"
SIZE = (96, 96)
MIN_PSNR_DB = 40.0  # the player's bound against the Python runtime (tests/test_web_player.py): 3 levels of 255
TSC = WEB / "node_modules" / "typescript" / "bin" / "tsc"

APP_TS = """\
import { ARKIT_BLENDSHAPES, BundleError, Camera, Player, decodeAudio, readBundle } from 'gaussiantalker-web';
import type { Frame } from 'gaussiantalker-web';
import { DriveQueue, WireDrive, decodeFramePacket } from 'gaussiantalker-web/live';

export async function play(bytes: ArrayBuffer, canvas: HTMLCanvasElement): Promise<number> {
  const player = await Player.load(bytes, { width: 256, height: 256, graphs: 'wasm', background: [1, 1, 1] });
  const centre = await player.headCentre();
  player.setCamera(player.camera.orbited(20, 0, centre).dollied(0.9, centre));
  const drive = await player.driveFromAudio(await decodeAudio(bytes, player.sampleRate), player.sampleRate);
  const frame: Frame = await player.renderFrame(drive, 0, { output: 'rgba_float' });
  await player.renderToCanvas(drive, drive.frames - 1, canvas);
  const stream = await player.openAudioStream();
  const ready: number = await stream.push(new Float32Array(640));
  await player.release();
  return frame.width * ready + ARKIT_BLENDSHAPES.length;
}

export function live(message: ArrayBuffer, queue: DriveQueue): WireDrive | null {
  const packet = decodeFramePacket(message);
  queue.push(packet.drive);
  const shown = queue.take(packet.drive.pts);
  return shown ? new WireDrive(shown) : null;
}

export async function check(bytes: Uint8Array): Promise<string> {
  try {
    return (await readBundle(bytes, { name: 'x.gtb' })).name + Camera.name;
  } catch (error) {
    return error instanceof BundleError ? error.message : 'other';
  }
}
"""
# A misuse the declarations must refuse (a frame index that is a string, an output the player has not).
BAD_TS = """\
import { Player } from 'gaussiantalker-web';
export async function bad(player: Player): Promise<void> {
  const drive = player.driveFromMotion(null);
  await player.renderFrame(drive, '0', { output: 'png' });
}
"""
PAGE = """\
<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>an app of gaussiantalker-web</title>
<script type="importmap">
{"imports": {"gaussiantalker-web": "./node_modules/gaussiantalker-web/src/index.js",
             "onnxruntime-web/wasm": "./node_modules/onnxruntime-web/dist/ort.wasm.bundle.min.mjs",
             "onnxruntime-web/webgpu": "./node_modules/onnxruntime-web/dist/ort.webgpu.bundle.min.mjs",
             "fflate": "./node_modules/fflate/esm/browser.js"}}
</script>
<script type="module">
import { Player } from 'gaussiantalker-web';
window.play = async (bundleUrl, audioUrl, indexes) => {
  const player = await Player.load(bundleUrl, { width: WIDTH, height: HEIGHT });
  const drive = await player.driveFromAudioFile(await (await fetch(audioUrl)).arrayBuffer());
  const frames = [];
  for (const i of indexes) frames.push(Array.from((await player.renderFrame(drive, i)).pixels));
  await player.release();
  return { frames, count: drive.frames };
};
window.appReady = true;
</script></head><body></body></html>
""".replace("WIDTH", str(SIZE[0])).replace("HEIGHT", str(SIZE[1]))


def _npm() -> str:
    npm = shutil.which("npm")
    need(None if npm else "npm is not installed", BROWSER_INSTALL)
    need(None if TSC.is_file() else f"typescript is not installed in {WEB / 'node_modules'}: run `npm ci` in {WEB}",
         BROWSER_INSTALL)
    return npm


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def packed(tmp_path_factory) -> dict:
    """`npm pack`'s report of the tarball it wrote (filename, integrity, files), with its path."""
    npm = _npm()
    out = tmp_path_factory.mktemp("pack")
    result = _run([npm, "pack", "--json", "--pack-destination", str(out)], WEB)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)[0]
    return {**report, "path": out / report["filename"]}


@pytest.fixture(scope="module")
def app_dir(packed, tmp_path_factory) -> Path:
    """A scratch app that installs the tarball. Tests run offline, and npm resolves a new dependency's version from
    the registry, so the app's lockfile pins the player's dependencies as web/package-lock.json does (the npm cache
    `npm ci` in web/ filled holds them by integrity) and `npm ci --offline` installs it; an app online runs `npm
    install gaussiantalker-web-VERSION.tgz`."""
    app = tmp_path_factory.mktemp("app")
    spec = f"file:{packed['path']}"
    web_lock = json.loads((WEB / "package-lock.json").read_text())["packages"]
    packages = {name: entry for name, entry in web_lock.items() if name and not entry.get("dev")}
    packages["node_modules/gaussiantalker-web"] = {"version": packed["version"], "resolved": spec,
                                                   "integrity": packed["integrity"],
                                                   "dependencies": web_lock[""]["dependencies"]}
    manifest = {"name": "scratch-app", "private": True, "type": "module", "dependencies": {"gaussiantalker-web": spec}}
    packages[""] = {"name": "scratch-app", "dependencies": manifest["dependencies"]}
    (app / "package.json").write_text(json.dumps(manifest))
    (app / "package-lock.json").write_text(json.dumps({"name": "scratch-app", "lockfileVersion": 3,
                                                       "requires": True, "packages": packages}))
    result = _run([_npm(), "ci", "--offline", "--no-audit", "--no-fund", "--ignore-scripts"], app)
    assert result.returncode == 0, result.stderr
    return app


def test_the_tarball_holds_the_player_its_types_and_readme_only(packed):
    with tarfile.open(packed["path"]) as archive:
        names = {name.removeprefix("package/") for name in archive.getnames()}
    sources = {f"src/{p.name}" for p in (WEB / "src").glob("*.js")}
    assert sources <= names and {"src/index.js", "src/sort_worker.js", "src/mic_worklet.js"} <= sources
    assert {"types/index.d.ts", "types/live.d.ts", "README.md", "package.json"} <= names
    assert not {n for n in names if n.startswith(("harness/", "node_modules/"))}, names
    package = json.loads((WEB / "package.json").read_text())
    assert package["exports"]["."]["default"] == "./src/index.js" and "private" not in package


def _js_exports(source: str) -> set[str]:
    """Names an ES module exports (`export class|function|const NAME`, `export { A, B } [from ...]`)."""
    names = set(re.findall(r"^export (?:async )?(?:class|function|const) (\w+)", source, re.M))
    for group in re.findall(r"^export \{([^}]*)\}", source, re.M):
        names |= {name.strip() for name in group.split(",") if name.strip()}
    return names


@pytest.mark.parametrize(("module", "declarations"), [("index.js", "index.d.ts"), ("live.js", "live.d.ts")])
def test_the_declarations_name_every_export(module, declarations):
    """Each entry's declarations declare exactly what it exports (values; the types are the declarations' own)."""
    declared = set(re.findall(r"^export (?:class|function|const) (\w+)", (WEB / "types" / declarations).read_text(),
                              re.M))
    assert declared == _js_exports((WEB / "src" / module).read_text())


def test_an_app_compiles_against_the_declarations(app_dir):
    """`tsc --strict` on an app using the API (the package resolved through its `exports`), and the same compiler
    refusing a misuse, so the declarations are really checked."""
    options = ["--strict", "--noEmit", "--target", "es2022", "--module", "nodenext", "--moduleResolution", "nodenext",
               "--lib", "es2022,dom", "--skipLibCheck", "false"]
    (app_dir / "app.ts").write_text(APP_TS)
    result = _run(["node", str(TSC), *options, "app.ts"], app_dir)
    assert result.returncode == 0, result.stdout + result.stderr
    (app_dir / "bad.ts").write_text(BAD_TS)
    result = _run(["node", str(TSC), *options, "bad.ts"], app_dir)
    assert result.returncode != 0 and "bad.ts" in result.stdout, result.stdout
    assert "'string' is not assignable to parameter of type 'number'" in result.stdout, result.stdout


def test_a_page_of_the_app_plays_a_bundle_like_the_python_runtime(app_dir, small_export):
    """The installed package in a page of the scratch app, importing it by name: the demo speech through the small
    speaker's translator, frames 0 and 60 within 3 levels of TalkingHead's GL frames."""
    need_chromium()
    from gaussiantalker.runtime import TalkingHead
    from tools.browser.chromium import Chromium
    from tools.browser.web_harness import HarnessServer

    (app_dir / "index.html").write_text(PAGE)
    audio = ROOT / "samples" / "demo_speech.wav"
    indexes = [0, 60]
    server = HarnessServer(app_dir, {})
    try:
        bundle_url, audio_url = server.add("small.gtb", small_export.path), server.add("speech.wav", audio)
        with Chromium(window=SIZE) as browser:
            browser.navigate(f"{server.url}/web/index.html")
            browser.evaluate("new Promise((resolve) => { (function poll() { if (window.appReady) resolve(1); "
                             "else setTimeout(poll, 20); })(); })", timeout=60)
            got = browser.evaluate(f"window.play({json.dumps(bundle_url)}, {json.dumps(audio_url)}, "
                                   f"{json.dumps(indexes)})", timeout=300)
    finally:
        server.close()
    with TalkingHead(small_export.path, resolution=SIZE, renderer="gl", composite=False) as head:
        drives = list(head.drives(audio))
        expected = [head.render(drives[i]) for i in indexes]
    assert got["count"] == len(drives)
    for pixels, reference in zip(got["frames"], expected, strict=True):
        frame = np.asarray(pixels, dtype=np.uint8).reshape(reference.shape)
        assert psnr_db(reference, frame) >= MIN_PSNR_DB
