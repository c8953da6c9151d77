"""What is imported on first use: package attributes (PEP 562) and the rows of tables.

Two shapes, one loader. A table row names its implementation as ``module:Class`` (the vehicle's
table, the MAVLink transports, the report's producers, the command providers) and `load` imports
it when the row is used, so reading a table costs nothing.

A package's ``__init__`` that imports its heavy modules makes every tool that touches the
package pay for them: `companion params show` loaded pymavlink, numpy, OpenCV and the log
converter through the package imports of its command providers, about 0.16 s of a 0.3 s
start. A package lists its public names with the module that defines each; the names load
when first read. Type checkers still see them through an ``if TYPE_CHECKING:`` import block
beside the table.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports", "load"]


def load(spec: str) -> Any:
    """The object that ``module:name`` names, imported now. A spec without a colon, a module
    that does not import or a name it lacks is a LookupError that names the spec and why."""
    module, sep, name = spec.partition(":")
    if not sep or not module or not name:
        raise LookupError(f"{spec!r} is not 'module:name'")
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError as exc:
        raise LookupError(f"cannot load {spec}: {exc}") from exc
    except AttributeError:
        raise LookupError(f"cannot load {spec}: module {module!r} has no {name!r}") from None


def lazy_exports(package: str, exports: Mapping[str, str]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of ``package`` for ``exports`` (name -> module)."""

    def getattr_(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    def dir_() -> list[str]:
        return sorted(exports)

    return getattr_, dir_
