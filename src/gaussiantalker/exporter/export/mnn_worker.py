"""Child process of `gt-export --mnn`: runs MNN's model converter on one ONNX file and nothing else.

Run as `python -m gaussiantalker.exporter.export.mnn_worker MODEL.onnx OUT.mnn`. The converter is called through its
library entry (`_tools.mnnconvert`, the function MNN's console script wraps), never the console script itself,
which installs a package and sends telemetry after converting (docs/mnn.md). Before MNN is imported, an audit
hook refuses every Python-level socket, process and download: anything that tries is reported, and the parent
fails the export. A separate process because the converter crashes (a segmentation fault) on some graphs,
which must become a clear error, not the end of `gt-export`.
"""

from __future__ import annotations

import json
import sys

# Audit events (docs.python.org "Audit events table") of network and process creation.
BLOCKED_EVENTS = ("socket.__new__", "socket.connect", "socket.getaddrinfo", "urllib.Request", "subprocess.Popen",
                  "os.system", "os.exec", "os.posix_spawn", "os.spawn", "os.fork", "os.forkpty", "pty.spawn")
REPORT_PREFIX = "gt-mnn-worker:"
BIZ_CODE = "gaussiantalker"


def forbid_side_effects(attempts: list[str]) -> None:
    """Refuse (PermissionError) and record in `attempts` every blocked event from now on, in this process."""

    def hook(event: str, args: tuple) -> None:
        if event in BLOCKED_EVENTS:
            attempts.append(event)
            raise PermissionError(f"{event} refused while converting to MNN (the export must stay offline)")

    sys.addaudithook(hook)


def convert(source: str, target: str) -> bool:
    """MNN's converter, ONNX -> .mnn; True when it reports success."""
    import _tools  # noqa: PLC0415 - MNN's native converter module, importable only with the `mnn` extra

    return bool(_tools.mnnconvert(["mnnconvert", "-f", "ONNX", "--modelFile", source, "--MNNModel", target,
                                   "--bizCode", BIZ_CODE]))


def main(argv: list[str]) -> int:
    attempts: list[str] = []
    forbid_side_effects(attempts)
    if len(argv) != 2:
        print("usage: python -m gaussiantalker.exporter.export.mnn_worker MODEL.onnx OUT.mnn", file=sys.stderr)
        return 2
    error = None
    try:
        ok = convert(argv[0], argv[1])
    except Exception as exc:  # a refused side effect, or MNN missing: reported to the parent, not a traceback
        ok, error = False, f"{type(exc).__name__}: {exc}"
    sys.stdout.flush()
    print(REPORT_PREFIX + json.dumps({"converted": ok, "blocked": attempts, "error": error}), flush=True)
    return 0 if ok and not attempts else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
