"""What the registries share (scene formats, projector kinds): hooks named lazily as
``"module:attr"`` strings, and registering an entry for the length of a block (tests)."""
from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


def resolve(target: str | Callable) -> Callable:
    """A callable as is; ``"module:attr[.attr...]"`` imported now (keeps registries cheap to import)."""
    if callable(target):
        return target
    mod, _, attr = target.partition(":")
    obj = importlib.import_module(mod)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@contextmanager
def registered_in(register: Callable[[Any], Any], unregister: Callable[[str], None], entry: Any) -> Iterator[Any]:
    """``entry`` registered with ``register`` inside the block only (removed by its ``name`` after)."""
    register(entry)
    try:
        yield entry
    finally:
        unregister(entry.name)
