"""`gt-bench`'s launcher: the benchmarks (tools/bench/app.py) run from the source checkout this package is installed
from, after checking for the `export` extra; the single command's mode flags still work (`bench_args`)."""

from __future__ import annotations

import sys

from .checkout import enter_checkout
from .extras import require_export_extra

# `gt-bench`'s subcommands (tools/bench/app.py), and the mode flags of the single command they replaced, in the order
# it checked them, each with the subcommand it is now and the options that mode read (the others it ignored).
BENCH_COMMANDS = ("frames", "sweep", "compare", "composite", "backends", "video", "clip-codecs", "clip-crf", "lam-web",
                  "avatar", "surface", "early-stop", "live", "live-clients", "renderers", "pipeline", "web-presets",
                  "live-batching", "blend-limit", "serve-attacks", "batch", "voice", "translator-stream",
                  "framing", "codings", "stream-calls", "live-pool", "voice-pushes")
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


def main() -> None:
    """`gt-bench`: the benchmarks, one subcommand each (the single command's mode flags still work)."""
    require_export_extra("gt-bench")  # before the checkout: a runtime-only install hears what to install first
    enter_checkout("gt-bench", "bench")
    args, note = bench_args(sys.argv[1:])
    if note:
        sys.stderr.write(note + "\n")
    sys.argv[1:] = args  # what the sweep records as its command
    from tools.bench.app import main_entry

    main_entry(args)
