"""JSON read strictly, for what users send (constraint files, server bodies): no NaN or Infinity, no key given
twice (Python's json keeps the last silently), nesting bounded by a one-line error."""
from __future__ import annotations

import json


def strict_json(text: str | bytes, constant_hint: str = ""):
    """Parsed JSON; ValueError for malformed JSON, NaN or Infinity (``constant_hint`` follows that message, e.g.
    how to say it instead), a key given twice in an object, or nesting Python cannot follow."""
    def no_constant(name: str):
        raise ValueError(f"{name} is not JSON{constant_hint}")

    def once(pairs: list) -> dict:
        keys = [k for k, _ in pairs]
        twice = next((k for k in keys if keys.count(k) > 1), None)
        if twice is not None:
            shown = repr(twice) if len(twice) <= 40 else repr(twice[:37]) + "..."
            raise ValueError(f"the key {shown} is given twice")
        return dict(pairs)

    try:
        return json.loads(text, parse_constant=no_constant, object_pairs_hook=once)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None
