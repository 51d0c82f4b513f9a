"""Bounds every reader of a user's JSON (bundle manifests, motion files) shares with the browser player's readers
(web/src/bundle.js, web/src/drive.js), so that both take a file the same way or refuse it alike
(docs/untrusted-input.md): how deep objects and arrays may nest, the largest integer, and no NaN or Infinity."""

from __future__ import annotations

# Objects and arrays nested deeper than this are refused (a manifest nests about 6 deep, a motion file 4): neither
# reader then walks, prints or recurses through a hostile nesting, and both agree where Python's parser would give up.
MAX_JSON_DEPTH = 64
# The largest integer a manifest may hold: 2^53 - 1, the largest JavaScript's numbers hold exactly.
MAX_JSON_INT = 2**53 - 1


def nests_deeper_than(value: object, limit: int = MAX_JSON_DEPTH) -> bool:
    """Whether a parsed JSON value holds an object or array more than `limit` deep (the top level is 1), walked
    without recursion."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict | list):
            if depth > limit:
                return True
            stack.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return False


def no_constant(name: str) -> float:
    """For json.loads(parse_constant=...): Python's json reads NaN, Infinity and -Infinity, which JSON does not have
    (and JavaScript's JSON.parse refuses)."""
    raise ValueError(f"{name} is not a JSON number")


__all__ = ["MAX_JSON_DEPTH", "MAX_JSON_INT", "nests_deeper_than", "no_constant"]
