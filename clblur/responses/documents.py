"""Response specs and JSON documents: parsing, saving and per-channel sets.

A spec is ``linear``, ``exp``, ``exp:K``, ``gamma:G``, ``srgb``, a response JSON path, a JSON
document or a ``Response``.  Parameters outside ``RANGES`` are rejected with a one-line
``clblur.errors.InputError``.  ``per_channel`` gives one device-ready response per image channel.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

from clblur.errors import InputError, InputTypeError
from clblur.responses.base import FORMAT_VERSION, KIND_CODES, RANGES, Response
from clblur.responses.emor import Emor
from clblur.responses.families import (
    ExpOffset,
    ExpShape,
    GammaOffset,
    MonotoneSpline,
    Polynomial,
)
from clblur.responses.kernel_curves import SRGB, Exp, Gamma, Linear, Table

__all__ = ["FAMILY_CLASSES", "CHANNEL_SET_KIND", "for_device", "from_dict", "load_response",
           "response", "channel_set_to_dict", "save_channel_set", "per_channel",
           "check_spec"]


_BY_KIND = {"linear": Linear, "exp": Exp, "gamma": Gamma, "srgb": SRGB}
# every family a response document may name (device kinds and fitted families)
FAMILY_CLASSES = {**_BY_KIND, "exp-offset": ExpOffset, "gamma-offset": GammaOffset,
                  "exp-shape": ExpShape, "polynomial": Polynomial, "emor": Emor}


# the keys of a response document (Response.to_dict) and of a per-channel one, which has
# "channels" in place of "params" (channel_set_to_dict)
_DOCUMENT_KEYS = {"format", "version", "kind", "params"}
_CHANNEL_SET_KEYS = {"format", "version", "kind", "channels"}


def _check_keys(doc: dict) -> None:
    """Refuse keys outside the document's own set (a per-channel document's or a single
    response's): a key this reader does not take would be ignored, and the family's default
    used in its place: {"kind": "gamma", "gamma": 2.4} read as gamma 2.2, without a word."""
    if doc.get("kind") == CHANNEL_SET_KIND:
        unknown = sorted(set(doc) - _CHANNEL_SET_KEYS)
        if unknown:
            raise InputError(f"per-channel response document has unknown key(s) {unknown}")
        return
    unknown = sorted(set(doc) - _DOCUMENT_KEYS)
    if unknown:
        raise InputError(f"response document has unknown key(s) {unknown}; a family's "
                         "parameters go under 'params', e.g. {\"kind\": \"gamma\", "
                         "\"params\": {\"gamma\": 2.2}}")


def for_device(r: Response) -> Response:
    """``r`` itself for a kernel kind (``KIND_CODES``), else its dense ``Table``."""
    return r if r.kind in KIND_CODES else r.as_table()


def from_dict(doc: dict) -> Response:
    """Build a response from its JSON document (see ``Response.to_dict``)."""
    if not isinstance(doc, dict) or "kind" not in doc:
        raise InputError("response document must be a JSON object with a 'kind' key")
    _check_keys(doc)
    kind, params = doc["kind"], doc.get("params") or {}
    if not isinstance(params, dict):
        raise InputError(f"response document's 'params' must be an object of named "
                         f"parameters, got {params!r}")
    params = dict(params)
    if kind == "table":
        meta = params.get("meta") or {}
        try:
            if isinstance(meta, dict) and meta.get("family") == MonotoneSpline.family:
                extra = {k: v for k, v in meta.items()
                         if k not in ("family", "knots", "log_increments")}
                return MonotoneSpline(meta["knots"], meta["log_increments"], extra)
            return Table(params["exposure"], params["value"], params.get("meta"))
        except KeyError as e:
            raise InputError(f"table response document lacks {e.args[0]!r}") from None
    if kind == CHANNEL_SET_KIND:
        raise InputError("this document holds one response per channel; use it where "
                         "per-channel responses are accepted (clblur.blur, clblur blur)")
    if kind not in FAMILY_CLASSES:
        raise InputError(f"unknown response kind {kind!r}; known: "
                         f"{', '.join(sorted({*KIND_CODES, *FAMILY_CLASSES}))}")
    if kind in ("polynomial", "emor", "exp-shape"):
        for key in ("coefficients", "warp"):
            if key in params and isinstance(params[key], list):
                params[key] = tuple(params[key])
    try:
        return FAMILY_CLASSES[kind](**params)
    except TypeError as e:
        raise InputError(f"bad parameters for {kind} response: {e}") from None


def load_response(path: str | os.PathLike) -> Response:
    """Read a response JSON file written by ``Response.save`` or ``clblur calibrate``."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise InputError(f"response file not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise InputError(f"cannot read response file {path}: {e}") from None
    return from_dict(doc)


def response(spec: str | os.PathLike | Response | dict) -> Response:
    """Parse a response spec: ``linear``, ``exp``, ``exp:K``, ``gamma:2.2``, ``srgb``,
    a path (``str`` or ``os.PathLike``) to a response JSON file, a JSON document, or a
    ``Response`` (returned as is)."""
    if isinstance(spec, Response):
        return spec
    if isinstance(spec, dict):
        return from_dict(spec)
    if isinstance(spec, os.PathLike):
        return load_response(spec)
    if not isinstance(spec, str):
        raise InputTypeError(f"response must be a name, a JSON path or a Response, got {spec!r}")
    name, _, arg = spec.partition(":")
    if name in ("linear", "srgb") and not arg:
        return _BY_KIND[name]()
    if name in ("exp", "gamma"):
        what, key = ("k", "k") if name == "exp" else ("exponent", "gamma")
        lo, hi = RANGES[key]
        letter = "K" if name == "exp" else "G"
        expected = f"{name}:{letter} with {letter} a number in [{lo:g}, {hi:g}]"
        if not arg:
            if name == "exp":
                return Exp()
            raise InputError(f"response spec {spec!r}: gamma response needs an exponent, "
                             f"expected {expected}, e.g. gamma:2.2")
        try:
            value = float(arg)
        except ValueError:
            raise InputError(f"response spec {spec!r}: {name} {what} must be a number, "
                             f"expected {expected}") from None
        try:
            return Exp(value) if name == "exp" else Gamma(value)
        except ValueError as e:
            raise InputError(f"response spec {spec!r}: {e}") from None
    if spec.endswith(".json") or os.path.sep in spec or os.path.exists(spec):
        return load_response(spec)
    raise InputError(f"unknown response {spec!r}; use linear, exp, exp:K, gamma:G, srgb "
                     "or a response JSON file")


CHANNEL_SET_KIND = "per-channel"


def channel_set_to_dict(responses: Sequence[Response]) -> dict:
    """A JSON document holding one response per channel (written by ``clblur calibrate``)."""
    return {"format": "clblur-response", "version": FORMAT_VERSION, "kind": CHANNEL_SET_KIND,
            "channels": [r.to_dict() for r in responses]}


def save_channel_set(path: str | os.PathLike, responses: Sequence[Response]) -> None:
    """Write per-channel responses as one JSON file (atomically)."""
    from clblur.io import atomic_write_text

    atomic_write_text(Path(path), json.dumps(channel_set_to_dict(responses), indent=2) + "\n")


def _channel_set(spec) -> list[Response] | None:
    """The responses of a per-channel document (dict or JSON path), else None."""
    doc = spec
    if isinstance(spec, (str, os.PathLike)) and str(spec).endswith(".json") \
            and Path(spec).is_file():
        try:
            doc = json.loads(Path(spec).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
            raise InputError(f"cannot read response file {spec}: {e}") from None
    if not (isinstance(doc, dict) and doc.get("kind") == CHANNEL_SET_KIND):
        return None
    _check_keys(doc)
    channels = doc.get("channels")
    if not isinstance(channels, list) or not channels:
        raise InputError("per-channel response document needs a non-empty 'channels' list")
    return [from_dict(d) for d in channels]


def per_channel(spec, channels: int, kind: str = "channel(s)") -> list[Response]:
    """One response per channel: a single spec is shared, a sequence must match ``channels``;
    a per-channel document (``kind: per-channel``, e.g. from ``clblur calibrate``) acts as the
    sequence it holds.  ``kind`` names the channels counted, for the message."""
    if not isinstance(spec, (list, tuple, Response)):
        found = _channel_set(spec)
        if found is not None:
            spec = found
    if isinstance(spec, (list, tuple)):
        if len(spec) != channels:
            raise InputError(f"got {len(spec)} per-channel responses for an image with "
                             f"{channels} {kind}")
        return [for_device(response(s)) for s in spec]
    r = for_device(response(spec))
    return [r] * channels


def check_spec(spec, channels: int | None = None) -> None:
    """Refuse (``InputError``, one line) a response spec that no image could take, before any
    work: ``channels`` is the image's colour channel count where known, else any count an
    image may have (1, 3 or 4; a per-channel document fits only its own)."""
    errors = []
    for count in (1, 3, 4) if channels is None else (channels,):
        try:
            per_channel(spec, count)
            return
        except (ValueError, TypeError) as e:
            errors.append(" ".join(str(e).split()))
    text = errors[0]
    if len(set(errors)) > 1:  # only the count failed, and the image is not known yet
        text = (errors[0].split(" for an image")[0] + "; a per-channel document needs one "
                "per colour channel of the images (1, 3 or 4)")
    raise InputError(text)
