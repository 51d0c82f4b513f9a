"""Avatar zips as LAM_WebRender and OpenAvatarChat ship them: the members at the top or inside one folder, with
macOS's resource-fork junk (__MACOSX/, .DS_Store, ._*) ignored."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

from gaussiantalker.sdk.errors import ImportFormatError

# Largest member read into memory: far above a 100k-Gaussian avatar, small enough to refuse a zip bomb.
MAX_MEMBER_BYTES = 2 << 30


def _junk(name: str) -> bool:
    parts = name.split("/")
    return parts[0] == "__MACOSX" or parts[-1] in (".DS_Store", "") or parts[-1].startswith("._")


def read_avatar_zip(path: str | os.PathLike, required: tuple[str, ...], optional: tuple[str, ...] = ()
                    ) -> dict[str, bytes]:
    """{member name: bytes} of the `required` and `optional` members found (by file name, at the top of the zip
    or all inside one folder); ImportFormatError naming the zip and the missing or ambiguous member."""
    path = Path(path)
    if not path.is_file():
        raise ImportFormatError(f"avatar {path} does not exist")
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise ImportFormatError(f"avatar {path} is not a readable zip file: {exc}") from None
    with archive:
        entries = [info for info in archive.infolist() if not info.is_dir() and not _junk(info.filename)]
        folders = {info.filename.rpartition("/")[0] for info in entries
                   if info.filename.rpartition("/")[2] in required}
        if len(folders) > 1:
            raise ImportFormatError(f"avatar {path} holds {required[0]} in several folders "
                                    f"({', '.join(sorted(f or '<top>' for f in folders))}): one avatar per zip")
        folder = next(iter(folders), "")
        members = {}
        for info in entries:
            directory, _, name = info.filename.rpartition("/")
            if directory == folder and name in required + optional:
                if info.file_size > MAX_MEMBER_BYTES:
                    raise ImportFormatError(f"avatar {path}: member {info.filename} is {info.file_size} bytes, "
                                            f"over the {MAX_MEMBER_BYTES} byte limit")
                try:
                    members[name] = archive.read(info)
                except (zipfile.BadZipFile, OSError, EOFError) as exc:
                    raise ImportFormatError(f"avatar {path}: member {info.filename} is damaged: {exc}") from None
    missing = [name for name in required if name not in members]
    if missing:
        where = f"folder {folder}/" if folder else "the top of the zip"
        raise ImportFormatError(f"avatar {path} lacks {', '.join(missing)} (looked in {where}; a LAM avatar zip "
                                f"holds {', '.join(required)})")
    return members


__all__ = ["read_avatar_zip"]
