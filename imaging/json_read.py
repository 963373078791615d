"""Reading JSON that comes from outside: every way a text can fail to parse is one error type.

``json.loads`` raises :class:`json.JSONDecodeError` for malformed text, but a :class:`RecursionError`
for arrays or objects nested past Python's recursion limit and a plain :class:`ValueError` for an
integer of more digits than Python converts: :func:`parse_json` reports all three as a
``JSONDecodeError``, which the readers of configs, manifests and headers already turn into their
one-line errors.
"""
from __future__ import annotations

import json
from typing import Any


def parse_json(text: str | bytes) -> Any:
    """``json.loads(text)``; raises :class:`json.JSONDecodeError` for anything it cannot parse."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        raise
    except RecursionError:
        raise json.JSONDecodeError("arrays or objects nested too deeply", "", 0) from None
    except ValueError as exc:
        raise json.JSONDecodeError(str(exc).splitlines()[0] if str(exc) else "invalid JSON", "", 0) from None
