"""Choosing the headset lens: the shipped lenses and :func:`load_lens`, which turns one spec into a
:class:`Lens` (its PSF bank and, where one was fitted, its pre-warp LUT), and
:func:`effects_for_lens`, which makes a pipeline's effects simulate that lens.

A lens spec is one of
- a shipped lens name (:data:`SHIPPED_LENSES`: ``"cardboard"``, ``"compact"``);
- a path to a PSF bank (``.safetensors``, :meth:`PSFBank.load`); a pre-warp LUT fitted for it is
  taken from ``<bank stem>_prewarp_lut.safetensors`` next to it (``my_psf_bank.safetensors`` also
  finds ``my_prewarp_lut.safetensors``), else from the shipped LUTs by bank fingerprint;
- a path to a JSON prescription (an object with ``"surfaces"``, see
  :data:`.prescription.CARDBOARD`): its bank is traced on load (:func:`.generate.build_bank`);
- a path to a JSON distortion profile (:mod:`.profiles`: an object whose ``kind`` is a profile form);
- a :class:`Lens` or a :class:`PSFBank`; None: ``"cardboard"``.

Loading never runs code: banks and LUTs are safetensors, prescriptions and profiles plain JSON.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Iterable, Literal, Mapping, NamedTuple, Union

from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import read_header

from ..bank_maps import DISPLAY_LUT_FORMAT_VERSION, DISPLAY_LUT_KIND, BankMap, bank_fingerprint
from ..stage import Stage
from .bank import PSFBank
from .generate import build_bank
from .prescription import CARDBOARD, Prescription
from .profiles import PROFILE_KINDS, bank_from_profile, is_profile, load_profile

__all__ = ["Lens", "LensSpec", "SHIPPED_LENSES", "DEFAULT_LENS", "load_lens", "effects_for_lens", "shipped_prescription",
           "prewarp_for_bank", "check_lens_spec"]


class ShippedLens(NamedTuple):
    """Files of a shipped lens in ``controlgs_adapter/data``: its PSF bank, its fitted pre-warp LUT and
    its prescription (None: :data:`.prescription.CARDBOARD`)."""

    bank: str
    prewarp: str
    prescription: str | None


#: the lenses shipped with the library, by name
SHIPPED_LENSES: dict[str, ShippedLens] = {
    "cardboard": ShippedLens("cardboard_psf_bank.safetensors", "cardboard_prewarp_lut.safetensors", None),
    "compact": ShippedLens("compact_psf_bank.safetensors", "compact_prewarp_lut.safetensors", "compact_prescription.json"),
}
#: the lens of the paper and of every default
DEFAULT_LENS = "cardboard"
#: largest JSON lens file read (a prescription is a few hundred bytes, a profile a few kilobytes)
LENS_JSON_MAX_BYTES = 16 << 20
LensKind = Literal["shipped", "bank", "prescription", "profile"]


@dataclass(frozen=True, eq=False)
class Lens:
    """A headset lens ready for the pipeline.

    Attributes:
        spec: what names it (recorded in a run): the shipped name, or the path as given.
        bank: its :class:`PSFBank` (3 primaries).
        prewarp: path of the pre-warp LUT fitted for ``bank`` (``controlgs optics fit-prewarp``), or None
            (the pipeline then uses the bank's chief rays, with a warning).
        kind: where it came from: ``"shipped"``, ``"bank"`` (a bank file or object), ``"prescription"``
            (traced on load) or ``"profile"`` (a distortion profile).
    """

    spec: str
    bank: PSFBank
    prewarp: Path | None
    kind: LensKind

    @property
    def is_default(self) -> bool:
        """True for the shipped Cardboard lens (the pipeline's built-in defaults already simulate it)."""
        return self.kind == "shipped" and self.spec == DEFAULT_LENS


LensSpec = Union[str, "os.PathLike[str]", Lens, PSFBank, None]


def _data_file(name: str) -> Path:
    """A file of ``controlgs_adapter/data`` (it may not exist)."""
    return Path(str(resources.files("controlgs_adapter.data").joinpath(name)))


def shipped_prescription(name: str) -> dict[str, Any]:
    """The prescription of shipped lens ``name`` (a JSON object, as :class:`Prescription` takes)."""
    entry = _shipped(name)
    if entry.prescription is None:
        return dict(CARDBOARD)
    path = _data_file(entry.prescription)
    if not path.is_file():
        raise InputValueError(f"lens {name}: its prescription {entry.prescription} is not installed")
    spec = _read_json(path)
    if "surfaces" not in spec:
        raise FileFormatError(f"{path}: a prescription must be a JSON object with 'surfaces'")
    return spec


def _shipped(name: str) -> ShippedLens:
    if name not in SHIPPED_LENSES:
        raise InputValueError(f"lens {name}: not a shipped lens ({', '.join(SHIPPED_LENSES)})")
    return SHIPPED_LENSES[name]


def prewarp_for_bank(bank: PSFBank, candidates: Iterable[Path] = ()) -> Path | None:
    """The first pre-warp LUT fitted for ``bank`` (its header's ``meta.bank`` is the bank's fingerprint)
    among ``candidates`` (files that do not exist are skipped), then the shipped lenses' LUTs; None if none is."""
    shipped = [_data_file(entry.prewarp) for entry in SHIPPED_LENSES.values()]
    fingerprint = None
    for path in [*candidates, *shipped]:
        if path.is_file():
            fingerprint = fingerprint or bank_fingerprint(bank)
            meta = read_header(path, kind=DISPLAY_LUT_KIND, max_version=DISPLAY_LUT_FORMAT_VERSION).get("meta")
            if isinstance(meta, dict) and meta.get("bank") == fingerprint:
                return path
    return None


def _neighbour_luts(bank_file: Path) -> list[Path]:
    """Where a LUT fitted for the bank in ``bank_file`` is looked for: ``<stem>_prewarp_lut.safetensors``
    next to it, and with a ``_psf_bank`` stem ending dropped (the shipped files' naming)."""
    stem = bank_file.name.removesuffix(".safetensors")
    names = [f"{stem}_prewarp_lut.safetensors"]
    if stem.endswith("_psf_bank"):
        names.append(f"{stem.removesuffix('_psf_bank')}_prewarp_lut.safetensors")
    return [bank_file.with_name(n) for n in names]


def _read_json(path: Path) -> dict[str, Any]:
    """A JSON object from ``path`` (size-limited); :class:`FileFormatError` naming the file otherwise."""
    try:
        size = path.stat().st_size
        if size > LENS_JSON_MAX_BYTES:
            raise FileFormatError(f"{path}: {size} bytes, larger than a lens file's {LENS_JSON_MAX_BYTES}")
        spec = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as e:
        raise FileFormatError(f"{path}: not a JSON lens file ({type(e).__name__}: {e})") from None
    if not isinstance(spec, dict):
        raise FileFormatError(f"{path}: a lens file must be a JSON object, got a JSON {type(spec).__name__}")
    return spec


def _profile_bank(path: Path, spec: dict[str, Any]) -> PSFBank:
    """The bank of a distortion profile (:mod:`.profiles`: chief rays only, every PSF an impulse)."""
    if not is_profile(spec):
        raise FileFormatError(f"{path}: neither a prescription (an object with 'surfaces') nor a distortion profile "
                              f"(an object whose 'kind' is one of {', '.join(PROFILE_KINDS)})")
    try:
        return bank_from_profile(load_profile(path))
    except InputValueError as e:  # the profile's map itself (it names the file)
        raise FileFormatError(str(e)) from None


def check_lens_spec(spec: str, what: str = "lens") -> None:
    """Refuse a lens ``spec`` that cannot name a lens, without loading it: neither a shipped name (with its
    bank installed) nor an existing ``.safetensors`` or ``.json`` file; one line starting ``<what> <spec>:``."""
    if spec in SHIPPED_LENSES:
        if not _data_file(SHIPPED_LENSES[spec].bank).is_file():
            raise InputValueError(f"{what} {spec}: its PSF bank {SHIPPED_LENSES[spec].bank} is not installed")
        return
    path = Path(spec)
    if not path.is_file():
        looks_like_name = not path.suffix and len(path.parts) == 1 and not path.exists()
        why = (f"not a shipped lens ({', '.join(SHIPPED_LENSES)}) nor a file" if looks_like_name
               else "not a regular file" if path.exists() else "no such file")
        raise InputValueError(f"{what} {spec}: {why}")
    if path.suffix.lower() not in (".safetensors", ".json"):
        raise FileFormatError(f"{path}: not a lens file: expected a PSF bank (.safetensors), a prescription or a "
                              "distortion profile (.json)")


def load_lens(spec: LensSpec = None) -> Lens:
    """The :class:`Lens` a spec names (module docstring); a prescription's bank is traced here (tens of
    seconds to minutes; one line on stdout says so). Errors: :class:`InputValueError` for an unknown name,
    :class:`FileFormatError` naming a missing or malformed file."""
    if spec is None:
        spec = DEFAULT_LENS
    if isinstance(spec, Lens):
        return spec
    if isinstance(spec, PSFBank):
        return Lens(f"psf-bank:{bank_fingerprint(spec)}", spec, prewarp_for_bank(spec), "bank")
    if not isinstance(spec, (str, os.PathLike)):
        raise InputValueError(f"lens must be a shipped lens name, a path, a Lens or a PSFBank, got {type(spec).__name__}")
    text = os.fspath(spec)
    check_lens_spec(text)
    if text in SHIPPED_LENSES:
        entry = SHIPPED_LENSES[text]
        bank = PSFBank.default() if text == DEFAULT_LENS else PSFBank.load(_data_file(entry.bank))
        lut = _data_file(entry.prewarp)
        return Lens(text, bank, lut if lut.is_file() else None, "shipped")
    path = Path(text)
    if path.suffix.lower() == ".safetensors":
        bank = PSFBank.load(path)
        return Lens(text, bank, prewarp_for_bank(bank, _neighbour_luts(path)), "bank")
    content = _read_json(path)
    if "surfaces" in content:
        try:
            rx = Prescription(content)
        except InputValueError as e:
            raise FileFormatError(f"{path}: {e}") from None
        print(f"lens {path}: tracing its PSF bank from the prescription (tens of seconds to minutes); trace it once "
              f"with `controlgs optics build-bank --lens {path} --out BANK.safetensors` and give --lens BANK.safetensors",
              flush=True)
        try:
            bank = build_bank(rx)
        except InputValueError as e:  # e.g. a field with no chief ray: the file is what is wrong
            raise FileFormatError(f"{path}: {e}") from None
        return Lens(text, bank, prewarp_for_bank(bank), "prescription")
    bank = _profile_bank(path, content)
    return Lens(text, bank, prewarp_for_bank(bank, _neighbour_luts(path.with_suffix(".safetensors"))), "profile")


#: options of ``{"lens": {...}}`` that build the lens from the optics (:meth:`.lens.LensPrewarp.for_optics`)
LENS_FOR_OPTICS = frozenset({"source", "basis", "lut", "gain", "supersample"})


def _on(value: Any) -> bool:
    return value is not None and value is not False


def effects_for_lens(effects: Mapping[str, Any] | Iterable[str], lens: LensSpec = None) -> dict[str, Any]:
    """``effects`` (as :meth:`Pipeline.from_config` takes them) made to simulate ``lens`` (any spec of
    :func:`load_lens`; None: unchanged, the shipped Cardboard lens of the defaults).

    - ``optics`` (on): ``{"bank": lens.bank}`` (with its other options kept); an optics stage or options
      that already name another bank are refused.
    - ``lens`` (on) with the optics: the LUT fitted for the bank (``{"lut": lens.prewarp}``) unless the
      options name one or ask for ``"chief_rays"``; without a fitted LUT, the bank's chief rays (warning).
    - ``lens`` (on) without the optics: the bank's chief rays (:class:`BankMap`), except for the Cardboard
      lens (the analytic radial map) or when the options name a map or coefficients.

    Returns a new dict; ``effects`` is not changed.
    """
    out: dict[str, Any] = dict(effects) if isinstance(effects, Mapping) else {n: True for n in effects}
    if lens is None:
        return out
    lens = load_lens(lens)
    optics = out.get("optics")
    if isinstance(optics, Stage) or (isinstance(optics, Mapping) and "bank" in optics):
        given = optics.get("bank") if isinstance(optics, Mapping) else getattr(optics, "bank", None)
        if given is not lens.bank:
            raise InputValueError(f"effects['optics'] already names its PSF bank; give the lens either there or as "
                                  f"lens= (got lens {lens.spec!r})")
    elif optics is True or isinstance(optics, Mapping):
        out["optics"] = {**(optics if isinstance(optics, Mapping) else {}), "bank": lens.bank}
    foveation = out.get("foveation")
    if foveation is True or (isinstance(foveation, Mapping) and not {"bank", "angles"} & set(foveation)):
        out["foveation"] = {**(foveation if isinstance(foveation, Mapping) else {}), "bank": lens.bank}
    value = out.get("lens")
    if not _on(value) or isinstance(value, Stage):
        return out
    options = dict(value) if isinstance(value, Mapping) else {}
    if _on(out.get("optics")):
        if (lens.prewarp is not None and set(options) <= LENS_FOR_OPTICS and "lut" not in options
                and options.get("source", "fitted") == "fitted"):
            out["lens"] = {**options, "lut": str(lens.prewarp)}
    elif not lens.is_default and not {"prewarp_map", "coefficients"} & set(options):
        out["lens"] = {**options, "prewarp_map": BankMap(lens.bank)}
    return out
