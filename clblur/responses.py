"""Camera response models: normalised pixel value <-> linear exposure.

Conventions
-----------
* ``forward(x)`` maps linear exposure ``x >= 0`` (time x irradiance, arbitrary units) to a
  normalised pixel value ``v`` in [0, 1] (code value / Imax).
* ``inverse(v)`` maps ``v`` back to exposure.  It may be infinite at ``v == 1`` (the paper's
  Eq. 3 reaches Imax only at infinite exposure); the blur's saturation policy handles that.
* The ``linear`` response is unbounded: it passes any real value through, so scene-linear float
  images (values above 1) are blurred as they are.  Every other response clips ``v`` to [0, 1].

Every model shares this small interface, so the numpy reference and the OpenCL kernels read the
same description (``device_code``) and calibrated curves of any family run as a ``table``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMAT_VERSION = 1

# Response kind codes; the kernels get them as -D options (clblur/opencl/constants.py).
KIND_CODES = {"linear": 0, "exp": 1, "gamma": 2, "srgb": 3, "table": 4}


class Response:
    """Base class: a monotone increasing map between exposure and normalised value."""

    kind: str = ""
    bounded: bool = True

    def forward(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def inverse(self, v: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def params(self) -> dict:
        return {}

    def device_params(self) -> tuple[float, ...]:
        """Up to four float parameters the kernels read (see clblur/opencl/response.cl)."""
        return ()

    def to_dict(self) -> dict:
        return {"format": "clblur-response", "version": FORMAT_VERSION, "kind": self.kind,
                "params": self.params()}

    def save(self, path: str | os.PathLike) -> None:
        """Write the response as a small JSON document (atomically)."""
        from clblur.io import atomic_write_text

        atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=2) + "\n")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Response) and self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(json.dumps(self.to_dict(), sort_keys=True))

    def __repr__(self) -> str:
        p = ", ".join(f"{k}={v!r}" for k, v in self.params().items() if k != "exposure"
                      and k != "value")
        return f"{type(self).__name__}({p})"


def _positive_finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    return value


class Linear(Response):
    """Identity response: the conventional box blur (the paper's Eq. 7)."""

    kind = "linear"
    bounded = False

    def forward(self, x):
        return np.asarray(x, dtype=np.float64)

    def inverse(self, v):
        return np.asarray(v, dtype=np.float64)


@dataclass(frozen=True, eq=False, repr=False)
class Exp(Response):
    """The paper's Eq. 3, normalised by Imax: ``v = 1 - exp(-k x)``.

    ``k`` only sets the unit of exposure.  When the static and the blurred image share one
    exposure it cancels in Eq. 9: ``g = 1 - prod_j (1 - f_j) ** w_j`` (a weighted geometric
    mean of ``1 - f``), whatever ``k`` is.
    """

    k: float = 1.0
    kind = "exp"

    def __post_init__(self):
        object.__setattr__(self, "k", _positive_finite("exp response k", self.k))

    def forward(self, x):
        return -np.expm1(-self.k * np.asarray(x, dtype=np.float64))

    def inverse(self, v):
        with np.errstate(divide="ignore"):
            return -np.log1p(-np.asarray(v, dtype=np.float64)) / self.k

    def params(self):
        return {"k": self.k}

    def device_params(self):
        return (self.k,)


@dataclass(frozen=True, eq=False, repr=False)
class Gamma(Response):
    """Power law ``v = x ** (1 / gamma)``; ``gamma:2.2`` is the classic display gamma."""

    gamma: float = 2.2
    kind = "gamma"

    def __post_init__(self):
        object.__setattr__(self, "gamma", _positive_finite("gamma exponent", self.gamma))

    def forward(self, x):
        return np.power(np.maximum(np.asarray(x, dtype=np.float64), 0.0), 1.0 / self.gamma)

    def inverse(self, v):
        return np.power(np.maximum(np.asarray(v, dtype=np.float64), 0.0), self.gamma)

    def params(self):
        return {"gamma": self.gamma}

    def device_params(self):
        return (self.gamma,)


class SRGB(Response):
    """IEC 61966-2-1 sRGB transfer function (linear segment below 0.04045 / 12.92).

    The standard rounds the exposure knee to 0.0031308; we use the exact image of the value
    knee 0.04045 so that ``forward(inverse(v)) == v`` holds across the knee too.
    """

    kind = "srgb"
    knee = 0.04045 / 12.92

    def forward(self, x):
        x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
        return np.where(x <= self.knee, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)

    def inverse(self, v):
        v = np.maximum(np.asarray(v, dtype=np.float64), 0.0)
        return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))


class Table(Response):
    """Any strictly increasing curve given as samples ``value = f(exposure)``.

    Between samples both directions interpolate linearly; outside they hold the end values.
    ``meta`` carries free-form provenance (e.g. the calibrated family and its parameters).
    """

    kind = "table"

    def __init__(self, exposure: Sequence[float], value: Sequence[float],
                 meta: dict | None = None):
        x = np.asarray(exposure, dtype=np.float64).ravel()
        v = np.asarray(value, dtype=np.float64).ravel()
        if x.size != v.size or x.size < 2:
            raise ValueError("table response needs equally long exposure and value lists "
                             f"with at least 2 samples, got {x.size} and {v.size}")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            raise ValueError("table response samples must be finite")
        if np.any(np.diff(x) <= 0) or np.any(np.diff(v) <= 0):
            raise ValueError("table response must be strictly increasing in both exposure "
                             "and value")
        if x[0] < 0 or v[0] < 0 or v[-1] > 1:
            raise ValueError("table response needs exposure >= 0 and values within [0, 1]")
        self.exposure, self.value, self.meta = x, v, dict(meta or {})

    def forward(self, x):
        return np.interp(np.asarray(x, dtype=np.float64), self.exposure, self.value)

    def inverse(self, v):
        return np.interp(np.asarray(v, dtype=np.float64), self.value, self.exposure)

    def params(self):
        p = {"exposure": self.exposure.tolist(), "value": self.value.tolist()}
        if self.meta:
            p["meta"] = self.meta
        return p

    @classmethod
    def from_response(cls, response: Response, n: int = 1024, top: float = 1.0,
                      meta: dict | None = None) -> Table:
        """Sample another response densely in value (useful to export any model)."""
        v = np.linspace(0.0, top, n)
        return cls(response.inverse(v), v, meta=meta)


_BY_KIND = {"linear": Linear, "exp": Exp, "gamma": Gamma, "srgb": SRGB}


def from_dict(doc: dict) -> Response:
    """Build a response from its JSON document (see ``Response.to_dict``)."""
    if not isinstance(doc, dict) or "kind" not in doc:
        raise ValueError("response document must be a JSON object with a 'kind' key")
    kind, params = doc["kind"], dict(doc.get("params") or {})
    if kind == "table":
        try:
            return Table(params["exposure"], params["value"], params.get("meta"))
        except KeyError as e:
            raise ValueError(f"table response document lacks {e.args[0]!r}") from None
    if kind == CHANNEL_SET_KIND:
        raise ValueError("this document holds one response per channel; use it where "
                         "per-channel responses are accepted (clblur.blur, clblur blur)")
    if kind not in _BY_KIND:
        raise ValueError(f"unknown response kind {kind!r}; known: "
                         f"{', '.join(sorted(KIND_CODES))}")
    try:
        return _BY_KIND[kind](**params)
    except TypeError as e:
        raise ValueError(f"bad parameters for {kind} response: {e}") from None


def load_response(path: str | os.PathLike) -> Response:
    """Read a response JSON file written by ``Response.save`` or ``clblur calibrate``."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"response file not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise ValueError(f"cannot read response file {path}: {e}") from None
    return from_dict(doc)


def response(spec: str | Response | dict) -> Response:
    """Parse a response spec: ``linear``, ``exp``, ``exp:K``, ``gamma:2.2``, ``srgb``,
    a path to a response JSON file, a JSON document, or a ``Response`` (returned as is)."""
    if isinstance(spec, Response):
        return spec
    if isinstance(spec, dict):
        return from_dict(spec)
    if not isinstance(spec, str):
        raise TypeError(f"response must be a name, a JSON path or a Response, got {spec!r}")
    name, _, arg = spec.partition(":")
    if name in ("linear", "srgb") and not arg:
        return _BY_KIND[name]()
    if name == "exp":
        return Exp(float(arg)) if arg else Exp()
    if name == "gamma":
        if not arg:
            raise ValueError("gamma response needs an exponent, e.g. gamma:2.2")
        try:
            g = float(arg)
        except ValueError:
            raise ValueError(f"gamma exponent must be a number, got {arg!r}") from None
        return Gamma(g)
    if spec.endswith(".json") or os.path.sep in spec or os.path.exists(spec):
        return load_response(spec)
    raise ValueError(f"unknown response {spec!r}; use linear, exp, exp:K, gamma:G, srgb "
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
            raise ValueError(f"cannot read response file {spec}: {e}") from None
    if not (isinstance(doc, dict) and doc.get("kind") == CHANNEL_SET_KIND):
        return None
    channels = doc.get("channels")
    if not isinstance(channels, list) or not channels:
        raise ValueError("per-channel response document needs a non-empty 'channels' list")
    return [from_dict(d) for d in channels]


def per_channel(spec, channels: int) -> list[Response]:
    """One response per channel: a single spec is shared, a sequence must match ``channels``;
    a per-channel document (``kind: per-channel``, e.g. from ``clblur calibrate``) acts as the
    sequence it holds."""
    if not isinstance(spec, (list, tuple, Response)):
        found = _channel_set(spec)
        if found is not None:
            spec = found
    if isinstance(spec, (list, tuple)):
        if len(spec) != channels:
            raise ValueError(f"got {len(spec)} per-channel responses for an image with "
                             f"{channels} channel(s)")
        return [response(s) for s in spec]
    r = response(spec)
    return [r] * channels
