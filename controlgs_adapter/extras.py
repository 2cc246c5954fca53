"""Optional dependencies (the package's extras), checked before a command starts its work.

colour-science puts a stand-in module in ``sys.modules["matplotlib"]`` when matplotlib is not
installed, so "importable" is not enough: a module counts only if it is a real, file-backed
package whose needed submodules import.
"""

from __future__ import annotations

import importlib

from .errors import MissingDependencyError

__all__ = ["EXTRAS", "missing_modules", "require"]

#: extra -> (import name, distribution name, submodules that must import)
EXTRAS: dict[str, tuple[tuple[str, str, tuple[str, ...]], ...]] = {
    "demo": (("skimage", "scikit-image", ("skimage.data",)), ("matplotlib", "matplotlib", ("matplotlib.pyplot",))),
    "optics": (("optiland", "optiland", ()),),
}


def _usable(name: str, submodules: tuple[str, ...]) -> bool:
    try:
        module = importlib.import_module(name)
        if not getattr(module, "__file__", None):  # a stand-in, not the installed package
            return False
        for sub in submodules:
            importlib.import_module(sub)
    except Exception:  # noqa: BLE001 - a broken install counts as missing, whatever it raises
        return False
    return True


def missing_modules(extra: str, only: tuple[str, ...] | None = None) -> list[str]:
    """Distribution names of ``extra``'s packages (or of those among ``only``, by import name)
    that are not usable here."""
    return [dist for name, dist, subs in EXTRAS[extra] if (only is None or name in only) and not _usable(name, subs)]


def require(extra: str, purpose: str, only: tuple[str, ...] | None = None) -> None:
    """Raise :class:`MissingDependencyError` (one line: what is missing, for what, what to install)
    unless every package of ``extra`` (or those named in ``only``) is usable."""
    missing = missing_modules(extra, only)
    if missing:
        raise MissingDependencyError(f"{purpose} needs {' and '.join(missing)}, which is not installed: "
                                     f"pip install 'controlgs-adapter[{extra}]'")
