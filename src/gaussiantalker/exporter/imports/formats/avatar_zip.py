"""Avatar zips as LAM_WebRender and OpenAvatarChat ship them: the members at the top or inside one folder, with
macOS's resource-fork junk (__MACOSX/, .DS_Store, ._*) ignored. Read within bounds (docs/untrusted-input.md,
"Avatar zips"): nothing is extracted, member names must stay inside the archive, sizes are checked before reading."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

from gaussiantalker.sdk.errors import ImportFormatError
from gaussiantalker.sdk.zip_reader import open_zip, read_member, unsafe_name

# Every member read, uncompressed, together: far above a 100k-Gaussian avatar, small enough to refuse a zip bomb.
MAX_AVATAR_BYTES = 2 << 30


def _junk(name: str) -> bool:
    parts = name.split("/")
    return parts[0] == "__MACOSX" or parts[-1] in (".DS_Store", "") or parts[-1].startswith("._")


def read_avatar_zip(path: str | os.PathLike, required: tuple[str, ...], optional: tuple[str, ...] = ()
                    ) -> dict[str, bytes]:
    """{member name: bytes} of the `required` and `optional` members found (by file name, at the top of the zip
    or all inside one folder); ImportFormatError naming the zip and the missing, ambiguous, unsafe or damaged
    member."""
    path = Path(path)
    with open_zip(path, ImportFormatError, "avatar") as archive:
        infos = archive.infolist()
        for info in infos:
            reason = unsafe_name(info.filename)
            if reason is not None:
                raise ImportFormatError(f"avatar {path}: member name {info.filename[:120]!r} {reason}; an avatar "
                                        "zip's members are relative paths inside it")
        entries = [info for info in infos if not info.is_dir() and not _junk(info.filename)]
        folders = {info.filename.rpartition("/")[0] for info in entries
                   if info.filename.rpartition("/")[2] in required}
        if len(folders) > 1:
            raise ImportFormatError(f"avatar {path} holds {required[0]} in several folders "
                                    f"({', '.join(sorted(f or '<top>' for f in folders))}): one avatar per zip")
        folder = next(iter(folders), "")
        wanted = [info for info in entries if info.filename.rpartition("/")[0] == folder
                  and info.filename.rpartition("/")[2] in required + optional]
        counts = Counter(info.filename for info in wanted)
        twice = sorted(name for name, count in counts.items() if count > 1)
        if twice:
            raise ImportFormatError(f"avatar {path} holds {twice[0]} twice: one avatar per zip")
        members, budget = {}, MAX_AVATAR_BYTES
        for info in wanted:
            data = read_member(archive, info, f"avatar {path}: member {info.filename}", ImportFormatError, budget)
            budget -= len(data)
            members[info.filename.rpartition("/")[2]] = data
    missing = [name for name in required if name not in members]
    if missing:
        where = f"folder {folder}/" if folder else "the top of the zip"
        raise ImportFormatError(f"avatar {path} lacks {', '.join(missing)} (looked in {where}; a LAM avatar zip "
                                f"holds {', '.join(required)})")
    return members


__all__ = ["MAX_AVATAR_BYTES", "read_avatar_zip"]
