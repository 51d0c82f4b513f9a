"""Console-script entry points of `gt-export` and `gt-import`: they check for the `export` extra (extras.py)
before importing anything that needs it."""

from __future__ import annotations

from .extras import require_export_extra


def gt_export() -> None:
    """`gt-export`: export (and verify) a speaker checkpoint."""
    require_export_extra("gt-export")
    from .export import main

    main()


def gt_import() -> None:
    """`gt-import`: turn an avatar trained elsewhere (LAM, GaussianAvatars) into a speaker checkpoint."""
    require_export_extra("gt-import")
    from .imports import main

    main()
