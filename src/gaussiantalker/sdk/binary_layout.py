"""Byte layouts of the fixed binary headers (the bundle's, the live wire's drive and frame packets), declared once as
named struct fields: the Python reader and writer use the struct, and web/src/generated.js carries each field's
offset and size to the browser player (docs/web.md, "One source")."""

from __future__ import annotations

import struct

Fields = tuple[tuple[str, str], ...]


def fields_struct(fields: Fields) -> struct.Struct:
    """The little-endian struct of `fields` ((name, struct code) in order, no implicit padding)."""
    return struct.Struct("<" + "".join(code for _, code in fields))


def field_layout(fields: Fields) -> dict[str, tuple[int, int]]:
    """Each field's (offset, size) in bytes."""
    layout, offset = {}, 0
    for name, code in fields:
        size = struct.calcsize("<" + code)
        layout[name] = (offset, size)
        offset += size
    return layout


__all__ = ["Fields", "field_layout", "fields_struct"]
