"""A thin program wrapper: kernels launched with named arguments.

In the spirit of gputools' ``OCLProgram.run_kernel``: ``program.run("integrate_box", queue,
global_size, local_size, plane=buf, lo=-12, ...)``.  The argument names and scalar types are
read from the kernel signatures in the ``.cl`` source (object-like macros expanded, so a macro
that stands for a shared parameter list is fine); each scalar is converted to its declared
dtype, each buffer argument accepts a ``pyopencl.Buffer`` or a ``pyopencl.array.Array``.  A
missing or unknown name is a ``TypeError`` naming it, not a silent shift of positional
arguments.

Conventions
-----------
* Sources: the ``*.cl`` files of this package, read with ``importlib.resources`` (so an
  installed wheel finds them), concatenated in ``KERNEL_FILES`` order.
* Build options: the shared constants (``clblur.opencl.constants.build_defines``) plus the
  variant flags the caller passes; one build per distinct option tuple (cached by the runtime).
* Builds go through :func:`build`, which drops pyopencl's content-free "Non-empty compiler
  output encountered" warning (PoCL on a CPU without AVX-512 says that its 16-lane vectors
  change the ABI, on every build of every run); ``PYOPENCL_COMPILER_OUTPUT=1`` still shows the
  compiler's own words, and ``bench/compiler_output.py`` lists them per program.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from importlib import resources

import numpy as np

__all__ = ["KERNEL_FILES", "Argument", "Program", "build", "kernel_signatures", "kernel_source"]

KERNEL_FILES = ("response.cl", "counts.cl", "integrate.cl")

_SCALARS = {"char": np.int8, "uchar": np.uint8, "short": np.int16, "ushort": np.uint16,
            "int": np.int32, "uint": np.uint32, "long": np.int64, "ulong": np.uint64,
            "float": np.float32, "double": np.float64}
_QUALIFIERS = {"const", "restrict", "__global", "global", "__constant", "constant",
               "__local", "local", "volatile", "unsigned"}


@dataclass(frozen=True)
class Argument:
    """One kernel parameter: its name and, for scalars, the numpy dtype (None: a buffer)."""

    name: str
    dtype: type | None


def kernel_source() -> str:
    """The program source: this package's ``.cl`` files in ``KERNEL_FILES`` order."""
    root = resources.files(__package__)
    return "\n".join(root.joinpath(name).read_text() for name in KERNEL_FILES)


def _strip_comments(source: str) -> str:
    source = re.sub(r"/\*.*?\*/", " ", source, flags=re.S)
    return re.sub(r"//[^\n]*", " ", source)


def _object_macros(source: str) -> dict[str, str]:
    """``#define NAME body`` without parameters (line continuations joined); last one wins."""
    joined = source.replace("\\\n", " ")
    macros = {}
    for m in re.finditer(r"^[ \t]*#[ \t]*define[ \t]+([A-Za-z_]\w*)(?![\w(])[ \t]*(.*)$", joined,
                         flags=re.M):
        macros[m[1]] = m[2].strip()
    return macros


def _expand(text: str, macros: dict[str, str]) -> str:
    for _ in range(8):  # nested macros, bounded
        new = re.sub(r"\b[A-Za-z_]\w*\b", lambda m: macros.get(m[0], m[0]), text)
        if new == text:
            return new
        text = new
    return text


def _argument(decl: str) -> Argument:
    decl = " ".join(decl.split())
    m = re.fullmatch(r"(.*?)([A-Za-z_]\w*)(\s*\[\s*\])?", decl)
    if m is None:
        raise ValueError(f"cannot parse kernel parameter {decl!r}")
    type_part, name = m[1], m[2]
    if "*" in type_part or m[3]:
        return Argument(name, None)
    words = [w for w in type_part.split() if w not in _QUALIFIERS]
    if len(words) != 1 or words[0] not in _SCALARS:
        raise ValueError(f"unsupported kernel parameter type in {decl!r}")
    return Argument(name, _SCALARS[words[0]])


def kernel_signatures(source: str) -> dict[str, tuple[Argument, ...]]:
    """Every ``__kernel`` function of ``source``: its parameters in order."""
    text = _strip_comments(source)
    macros = _object_macros(text)
    out = {}
    for m in re.finditer(r"(?:__kernel|\bkernel)\s+void\s+(\w+)\s*\(([^)]*)\)", text):
        params = _expand(m[2], macros)
        out[m[1]] = tuple(_argument(p) for p in params.split(",") if p.strip())
    return out


def build(context, source: str, options=()):
    """``pyopencl.Program(context, source).build(options)`` without pyopencl's generic
    "Non-empty compiler output encountered" warning: the build succeeded, and the warning
    does not say what the compiler said (``PYOPENCL_COMPILER_OUTPUT=1`` makes pyopencl warn
    with the compiler's text instead, which passes)."""
    import pyopencl as cl

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Non-empty compiler output encountered",
                                category=cl.CompilerWarning)
        return cl.Program(context, source).build(options=list(options))


def _buffer(value, name: str):
    data = getattr(value, "base_data", None)
    if data is not None:  # pyopencl.array.Array
        if getattr(value, "offset", 0):
            raise ValueError(f"kernel argument {name}: arrays with an offset are not supported")
        return data
    return value


class Program:
    """A built OpenCL program whose kernels take keyword arguments.

    Parameters
    ----------
    context : pyopencl.Context
    source : str
        OpenCL C source.
    options : sequence of str
        Build options.
    """

    def __init__(self, context, source: str, options):
        self.options = tuple(options)
        self.program = build(context, source, self.options)
        self.signatures = kernel_signatures(source)
        self._kernels: dict = {}

    def kernel(self, name: str):
        """The ``pyopencl.Kernel`` called ``name`` (one object per program, reused)."""
        if name not in self._kernels:
            self._kernels[name] = getattr(self.program, name)
        return self._kernels[name]

    def run(self, name: str, queue, global_size, local_size=None, *, global_offset=None,
            wait_for=None, **args):
        """Enqueue kernel ``name`` with its parameters given by name; return the event."""
        signature = self.signatures.get(name)
        if signature is None:
            raise KeyError(f"no kernel {name!r} in the program")
        wanted = {a.name for a in signature}
        unknown, missing = sorted(set(args) - wanted), sorted(wanted - set(args))
        if unknown or missing:
            raise TypeError(f"kernel {name}: unknown argument(s) {unknown}, missing {missing}")
        values = [_buffer(args[a.name], a.name) if a.dtype is None else a.dtype(args[a.name])
                  for a in signature]
        return self.kernel(name)(queue, tuple(global_size),
                                 None if local_size is None else tuple(local_size), *values,
                                 global_offset=global_offset, wait_for=wait_for)
