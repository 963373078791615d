"""Mutations of valid files: what a broken writer, a truncated copy or a hostile author makes of them.

Every mutation is a function of the bytes and a ``random.Random`` (so a run is reproducible from its
seed, and hypothesis can drive the choices and shrink them). Byte-level mutations (bit flips,
interesting integers, insertions, deletions, duplicated blocks, truncation, splices) favour a
file's *hot* region, its header, where one changed byte says something different rather than
only colouring a pixel. Text-level ones rewrite numbers and lines (PFM and RGBE headers, XML,
JSON); :func:`mutate_json` changes a parsed JSON value's leaves and keys (configs, manifests, a
checkpoint's header).
"""
from __future__ import annotations

import json
import random
import re
import struct
from collections.abc import Callable
from typing import Any

INTERESTING_INTS = (0, 1, 2, 3, 7, 8, 15, 16, 31, 32, 63, 64, 127, 128, 255, 256, 1023, 1024, 4096, 65535,
                    65536, 100000, 2**20, 2**24, 2**31 - 1, 2**31, 2**32 - 1, 2**32, 2**53, 2**63 - 1, 2**64 - 1,
                    -1, -2, -128, -2**31, -2**63)
INTERESTING_TEXT = ("0", "-1", "1", "65504", "100000", "99999999999", "2147483648", "18446744073709551616",
                    "1e308", "-1e308", "1e-320", "nan", "inf", "-inf", "0.0", "", "1.5", "4096", "-0")
_NUMBER = re.compile(rb"-?\d+(\.\d+)?([eE][-+]?\d+)?")


def _position(data: bytes, rnd: random.Random, hot: int) -> int:
    """A byte offset, in the first ``hot`` bytes three times in four."""
    if not data:
        return 0
    if hot and rnd.random() < 0.75:
        return rnd.randrange(min(hot, len(data)))
    return rnd.randrange(len(data))


def flip_bits(data: bytes, rnd: random.Random, hot: int) -> bytes:
    out = bytearray(data)
    for _ in range(rnd.choice((1, 1, 2, 4, 8))):
        if out:
            at = _position(out, rnd, hot)
            out[at] ^= 1 << rnd.randrange(8)
    return bytes(out)


def set_bytes(data: bytes, rnd: random.Random, hot: int) -> bytes:
    out = bytearray(data)
    at = _position(out, rnd, hot)
    out[at:at + 1] = bytes([rnd.choice((0, 1, 0x7F, 0x80, 0xFF, rnd.randrange(256)))])
    return bytes(out)


def set_integer(data: bytes, rnd: random.Random, hot: int) -> bytes:
    """An interesting integer written over 1, 2, 4 or 8 bytes, little or big endian."""
    width = rnd.choice((1, 2, 4, 8))
    value = rnd.choice(INTERESTING_INTS) % (1 << (8 * width))
    at = _position(data, rnd, hot)
    raw = value.to_bytes(width, rnd.choice(("little", "big")))
    return data[:at] + raw + data[at + width:]


def insert_bytes(data: bytes, rnd: random.Random, hot: int) -> bytes:
    at = _position(data, rnd, hot)
    n = rnd.choice((1, 2, 4, 16, 256))
    return data[:at] + bytes(rnd.choice((0, 0xFF, rnd.randrange(256))) for _ in range(n)) + data[at:]


def delete_bytes(data: bytes, rnd: random.Random, hot: int) -> bytes:
    at = _position(data, rnd, hot)
    return data[:at] + data[at + rnd.choice((1, 2, 4, 16, 256)):]


def duplicate_block(data: bytes, rnd: random.Random, hot: int) -> bytes:
    at = _position(data, rnd, hot)
    n = rnd.choice((4, 16, 64, 1024))
    return data[:at] + data[at:at + n] * rnd.choice((2, 3, 100)) + data[at:]


def truncate(data: bytes, rnd: random.Random, hot: int) -> bytes:
    return data[:rnd.choice((0, 1, 4, 8, 16, hot, len(data) // 2, max(0, len(data) - 1)))] if data else data


def number_text(data: bytes, rnd: random.Random, hot: int) -> bytes:
    """A number written in the text replaced by an interesting one (headers, XML, JSON)."""
    numbers = list(_NUMBER.finditer(data[:hot or len(data)])) or list(_NUMBER.finditer(data))
    if not numbers:
        return set_bytes(data, rnd, hot)
    m = rnd.choice(numbers)
    return data[:m.start()] + rnd.choice(INTERESTING_TEXT).encode() + data[m.end():]


def shuffle_lines(data: bytes, rnd: random.Random, hot: int) -> bytes:
    """A line of the text deleted, duplicated or swapped with the next."""
    lines = data.split(b"\n")
    if len(lines) < 2:
        return insert_bytes(data, rnd, hot)
    i = rnd.randrange(len(lines) - 1)
    how = rnd.randrange(3)
    if how == 0:
        del lines[i]
    elif how == 1:
        lines.insert(i, lines[i])
    else:
        lines[i], lines[i + 1] = lines[i + 1], lines[i]
    return b"\n".join(lines)


def splice(data: bytes, rnd: random.Random, hot: int, other: bytes = b"") -> bytes:
    """The start of ``data`` joined to the end of another seed (or of itself)."""
    other = other or data
    return data[:_position(data, rnd, hot)] + other[rnd.randrange(len(other) + 1):]


BYTE_MUTATIONS: tuple[Callable[[bytes, random.Random, int], bytes], ...] = (
    flip_bits, set_bytes, set_integer, set_integer, insert_bytes, delete_bytes, duplicate_block, truncate)
TEXT_MUTATIONS = (number_text, number_text, number_text, shuffle_lines, set_bytes, insert_bytes, delete_bytes,
                  truncate)


def mutate_bytes(data: bytes, rnd: random.Random, hot: int = 0, text: bool = False,
                 others: tuple[bytes, ...] = ()) -> bytes:
    """One to four stacked mutations of ``data`` (see the module notes)."""
    for _ in range(rnd.choice((1, 1, 1, 2, 2, 3, 4))):
        if others and rnd.random() < 0.05:
            data = splice(data, rnd, hot, rnd.choice(others))
            continue
        data = rnd.choice(TEXT_MUTATIONS if text else BYTE_MUTATIONS)(data, rnd, hot)
    return data


INTERESTING_JSON: tuple[Any, ...] = (0, -1, 1, 2**31, 2**63, 10**30, 1e308, -1e308, 0.5, True, False, None, "",
                                    "x" * 300, [], {}, [1, 2, 3], {"a": 1}, 4096, 100000, "../../etc/passwd",
                                    float("nan"), float("inf"))


def _leaves(value: Any, path: tuple = ()) -> list[tuple]:
    """Paths (tuples of keys and indices) of the values inside ``value`` (itself included, 16 levels
    deep at most, the first 64 items of a list)."""
    found = [path]
    if len(path) >= 16:  # below a deep nest inserted by an earlier mutation
        return found
    if isinstance(value, dict):
        for k, v in value.items():
            found += _leaves(v, path + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value[:64]):
            found += _leaves(v, path + (i,))
    return found


def _replace(value: Any, path: tuple, new: Any) -> Any:
    if not path:
        return new
    head, rest = path[0], path[1:]
    if isinstance(value, dict):
        return {**value, head: _replace(value[head], rest, new)}
    copy = list(value)
    copy[head] = _replace(copy[head], rest, new)
    return copy


def _delete(value: Any, path: tuple) -> Any:
    if len(path) == 1:
        if isinstance(value, dict):
            return {k: v for k, v in value.items() if k != path[0]}
        return [v for i, v in enumerate(value) if i != path[0]]
    head = path[0]
    if isinstance(value, dict):
        return {**value, head: _delete(value[head], path[1:])}
    copy = list(value)
    copy[head] = _delete(copy[head], path[1:])
    return copy


def mutate_json(value: Any, rnd: random.Random) -> Any:
    """``value`` with one to three leaves replaced, deleted, nested deeply or given a new key."""
    for _ in range(rnd.choice((1, 1, 2, 3))):
        path = rnd.choice(_leaves(value))
        how = rnd.randrange(6)
        if how <= 2 or not path:
            old = _get(value, path)
            if isinstance(old, (int, float)) and not isinstance(old, bool) and rnd.random() < 0.5:
                new = rnd.choice((old + 1, old - 1, old * 2, -old, old * 1000, 0))
            else:
                new = rnd.choice(INTERESTING_JSON)
            value = _replace(value, path, new)
        elif how == 3:
            value = _delete(value, path)
        elif how == 4:
            value = _replace(value, path, _nested(rnd.choice((10, 1000, 100000))))
        else:
            parent = path[:-1]
            target = _get(value, parent)
            if isinstance(target, dict):
                value = _replace(value, parent, {**target, rnd.choice(("extra", "__proto__", "x" * 40)): 1})
            elif isinstance(target, list):
                value = _replace(value, parent, target + target[:1] * rnd.choice((1, 1000)))
    return value


def _get(value: Any, path: tuple) -> Any:
    for key in path:
        value = value[key]
    return value


def _nested(depth: int) -> Any:
    out: Any = 0
    for _ in range(depth):
        out = [out]
    return out


def json_bytes(value: Any, rnd: random.Random) -> bytes:
    """``value`` serialised as JSON (non-finite floats as NaN/Infinity, as Python writes them);
    deep nesting that the encoder refuses is written by hand."""
    try:
        return json.dumps(value, indent=rnd.choice((None, 1))).encode()
    except (RecursionError, ValueError):
        depth = rnd.choice((1000, 100000))
        return b"[" * depth + b"]" * depth


def safetensors_with_header(data: bytes, header: dict[str, Any]) -> bytes:
    """A safetensors file with its JSON header replaced (the length prefix rewritten)."""
    (length,) = struct.unpack("<Q", data[:8])
    raw = json.dumps(header).encode()
    return struct.pack("<Q", len(raw)) + raw + data[8 + length:]
