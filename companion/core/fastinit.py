"""A cheaper constructor for the frozen dataclasses built on every sample.

The runtime hands every sample between threads as a frozen dataclass, so a reader's reference
is a consistent snapshot (`companion.core.state`). The price is in construction: the
`__init__` that `dataclasses` writes for a frozen class sets each field through
`object.__setattr__`, about 90 ns a field, and a lockstep flight builds some 600 such objects
per simulated second (truth, IMU samples, estimates, control outputs, servo exchanges): the
largest single Python-level cost after the flight model in a profile of it.

`fast_frozen` replaces that `__init__` with one of the same signature that stores the fields
straight into the instance's `__dict__` (or through the slot descriptors of a `slots=True`
class). Nothing else changes: assignment after construction still raises
`dataclasses.FrozenInstanceError`, and equality, hashing, `repr`, `replace` and `asdict` are
the dataclass's own. A class whose construction does more than store its arguments (a
`default_factory`, `__post_init__`, `init=False` or keyword-only fields) is refused, so the
fast path never silently skips work.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

__all__ = ["fast_frozen"]

T = TypeVar("T")

_SELF = "__fast_self__"


def fast_frozen(cls: type[T]) -> type[T]:
    """Give a frozen dataclass a constructor that stores its fields directly (see module)."""
    if not dataclasses.is_dataclass(cls) or not cls.__dataclass_params__.frozen:  # type: ignore[attr-defined]
        raise TypeError(f"fast_frozen: {cls.__name__} is not a frozen dataclass")
    if hasattr(cls, "__post_init__"):
        raise TypeError(f"fast_frozen: {cls.__name__} has __post_init__")
    fields = dataclasses.fields(cls)
    namespace: dict[str, Any] = {}
    params: list[str] = []
    for f in fields:
        if not f.init or f.kw_only or f.default_factory is not dataclasses.MISSING:
            raise TypeError(f"fast_frozen: {cls.__name__}.{f.name} is not a plain init field "
                            "(init=False, kw_only or default_factory)")
        if f.name == _SELF:
            raise TypeError(f"fast_frozen: {cls.__name__} has a field named {_SELF}")
        if f.default is dataclasses.MISSING:
            params.append(f.name)
        else:
            namespace[f"__default_{f.name}__"] = f.default
            params.append(f"{f.name}=__default_{f.name}__")
    slotted = "__slots__" in cls.__dict__
    if slotted:
        lines = []
        for f in fields:
            namespace[f"__set_{f.name}__"] = cls.__dict__[f.name].__set__
            lines.append(f" __set_{f.name}__({_SELF}, {f.name})")
    else:
        lines = [f" __fast_d__ = {_SELF}.__dict__"]
        lines += [f" __fast_d__[{f.name!r}] = {f.name}" for f in fields]
    if not fields:
        lines = [" pass"]
    source = f"def __init__({', '.join([_SELF, *params])}):\n" + "\n".join(lines) + "\n"
    exec(compile(source, f"<fast_frozen {cls.__qualname__}>", "exec"), namespace)  # noqa: S102
    init = namespace["__init__"]
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    init.__module__ = cls.__module__
    init.__doc__ = cls.__init__.__doc__
    init.__annotations__ = dict(getattr(cls.__init__, "__annotations__", {}))
    cls.__init__ = init  # type: ignore[method-assign]
    return cls
