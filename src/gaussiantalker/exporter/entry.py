"""Console-script entry points of the exporter side (`gt-export`, `gt-import`, `gt-bench`).

They check for the `export` extra before importing anything that needs it, so a runtime-only install
(`pip install gaussiantalker-sdk`, no torch) gets one line saying what to install instead of a traceback.
"""

from __future__ import annotations

import sys

# What the exporter side imports beyond the runtime's dependencies (the `export` extra of pyproject.toml).
EXPORT_EXTRA_MODULES = ("torch", "onnx", "onnxscript", "plyfile")
INSTALL_HINT = ('pip install torch==2.13.0 && pip install "gaussiantalker-sdk[export]" '
                "(torch first, so pip keeps the CPU build)")


def missing_export_modules() -> list[str]:
    """The export extra's modules that cannot be imported here."""
    missing = []
    for name in EXPORT_EXTRA_MODULES:
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    return missing


def _require_export_extra(command: str) -> None:
    """Exit with status 2 and one line on stderr when the export extra is not installed."""
    missing = missing_export_modules()
    if missing:
        sys.stderr.write(f"{command}: needs the 'export' extra ({', '.join(missing)} not installed): "
                         f"{INSTALL_HINT}\n")
        raise SystemExit(2)


def gt_export() -> None:
    """`gt-export`: export (and verify) a speaker checkpoint."""
    _require_export_extra("gt-export")
    from .cli import main

    main()


def gt_import() -> None:
    """`gt-import`: turn an avatar trained elsewhere (LAM) into a speaker checkpoint."""
    _require_export_extra("gt-import")
    from .import_cli import main

    main()


# `gt-bench`'s subcommands (bench/app.py), and the mode flags of the single command they replaced, in the order it
# checked them, each with the subcommand it is now and the options that mode read (the others it ignored).
BENCH_COMMANDS = ("frames", "sweep", "compare", "composite", "backends", "video", "clip-codecs", "clip-crf", "lam-web",
                  "avatar", "surface", "early-stop", "live", "live-clients", "renderers", "pipeline")
LEGACY_BENCH_MODES = (
    ("--backends", "backends", ("--checkpoint", "--sizes", "--seconds", "--rounds", "--out")),
    ("--composite", "composite", ("--checkpoint", "--seconds", "--rounds", "--out")),
    ("--sweep", "sweep", ("--checkpoint", "--gaussians", "--sweep-gaussians", "--skip-demo", "--cases", "--scene",
                          "--sizes", "--seconds", "--rounds", "--out")),
    ("--baseline", "compare", ("--baseline", "--gaussians", "--sizes", "--seconds", "--rounds", "--scaling",
                               "--play-seconds", "--json")),
)
FRAMES_OPTIONS = ("--checkpoint", "--gaussians", "--sizes", "--seconds", "--torch-frames", "--paper-translator",
                  "--json")
# The single command's options that took no value.
LEGACY_BENCH_FLAGS = ("--backends", "--composite", "--sweep", "--skip-demo", "--paper-translator")


def bench_args(argv: list[str]) -> tuple[list[str], str | None]:
    """`gt-bench`'s arguments with the single command's form rewritten to its subcommand: a mode flag becomes its
    subcommand (options that mode ignored are dropped), anything else runs `frames`; and the note to print."""
    if not argv or argv[0] in BENCH_COMMANDS or argv[0] == "--help":
        return (argv or ["frames"]), None
    names = {arg.split("=", 1)[0] for arg in argv}
    mode = next((m for m in LEGACY_BENCH_MODES if m[0] in names), None)
    if mode is None and "--help" in names:
        return argv, None
    flag, command, kept = mode or (None, "frames", FRAMES_OPTIONS)
    args, dropped, index = [command], [], 0
    while index < len(argv):
        arg = argv[index]
        name = arg.split("=", 1)[0]
        takes_value = name.startswith("--") and "=" not in arg and name not in LEGACY_BENCH_FLAGS
        span = argv[index: index + (2 if takes_value else 1)]
        if name in kept or name == "--help" or not name.startswith("--"):
            args += span
        elif name != flag:
            dropped.append(name)
        index += len(span)
    notes = [] if flag is None else [f"{flag} is now the subcommand `gt-bench {command}`; running that"]
    if dropped:
        notes.append(f"ignoring {', '.join(dropped)}, which `gt-bench {command}` does not take")
    return args, ("gt-bench: " + "; ".join(notes)) if notes else None


def gt_bench() -> None:
    """`gt-bench`: the benchmarks, one subcommand each (the single command's mode flags still work)."""
    _require_export_extra("gt-bench")
    args, note = bench_args(sys.argv[1:])
    if note:
        sys.stderr.write(note + "\n")
    sys.argv[1:] = args  # what the sweep records as its command
    from .bench.app import main_entry

    main_entry(args)
