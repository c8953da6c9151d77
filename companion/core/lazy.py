"""Package attributes imported on first use (PEP 562).

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

__all__ = ["lazy_exports"]


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
