"""Traced programs kept on disk, so a new process skips tracing the window solve.

Why. JAX's persistent compilation cache (:mod:`bcmocap.compilation_cache`) skips XLA's compilation, but
every new process still traces and lowers the window solve before it can look the compilation up: about
3 s of Python for optimistix's Levenberg–Marquardt loop around our structured normal equations, paid by
the first window of every ``bcmocap run`` (more than the window's own solve). Here the traced program is
exported once (:func:`jax.export.export`, StableHLO) and stored beside the compilation cache; a later
process with the same program deserialises it (milliseconds), and its compilation is a cache hit.

What decides the program, and so the file name (a SHA-256 of all of it):

- the static part of the arguments (everything that is not an array: term classes and settings, the
  skeleton's tree, solver options), pickled in full; and every array argument's shape, dtype and weak type;
- the code: the source of every ``bcmocap`` module and the versions of jax, jaxlib, equinox, optimistix,
  lineax and numpy; the JAX backend and its ``x64`` flag.

A program that refers to code outside these packages (a researcher's own residual term, a lambda) is
never stored: its code could change under the same key. Nor is one that cannot be exported (e.g. it holds
a host callback). Either way the function is simply traced, as without the cache.

A file starts with a line holding the SHA-256 of the rest. A file that is missing it, does not match it or
cannot be deserialised (truncated, overwritten, written by an older version) is dropped with a note on stderr,
and the program is traced again and stored anew.

The exported program computes exactly what the traced one does (the same StableHLO; a test compares the
results bit for bit).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import io
import os
import pickle
import sys
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax

from ..atomic import atomic_path

#: Packages whose code a stored program may refer to (their versions, or bcmocap's source, are in the key).
_KNOWN_PACKAGES = ("bcmocap", "jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy", "jaxlie",
                   "jaxtyping", "builtins", "collections", "functools", "operator", "enum", "typing", "math")
_VERSIONED = ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy", "jaxlie")
_FOLDER = "bcmocap_programs"
_MAGIC = b"bcmocap-program-1 "  # then the SHA-256 (hex) of everything after the first line

_loaded: dict[str, tuple] = {}  # key → (callable on the flat array arguments, output treedef), this process
_not_storable: set[str] = set()  # keys whose programs cannot be exported or run
_source_digests: dict[tuple, bytes] = {}  # bcmocap's files' (path, mtime, size) → SHA-256 of their source


class _UnknownCode(Exception):
    """The static part refers to code outside :data:`_KNOWN_PACKAGES`."""


class _KeyPickler(pickle.Pickler):
    """Pickles the static part, refusing classes and functions of unknown packages."""

    def reducer_override(self, obj):
        owner = obj if isinstance(obj, type) or callable(obj) and hasattr(obj, "__qualname__") else type(obj)
        module = getattr(owner, "__module__", None) or ""
        if module.split(".")[0] not in _KNOWN_PACKAGES or "<lambda>" in getattr(owner, "__qualname__", "") \
                or "<locals>" in getattr(owner, "__qualname__", ""):
            raise _UnknownCode(f"{module}.{getattr(owner, '__qualname__', owner)}")
        return NotImplemented


def _source_digest() -> bytes:
    """SHA-256 of bcmocap's source, read again whenever a file changed (a module edited and reloaded in a
    notebook changes it)."""
    package = Path(__file__).resolve().parents[1]
    paths = sorted(package.rglob("*.py"))
    stamp = tuple((str(p), p.stat().st_mtime_ns, p.stat().st_size) for p in paths)
    if stamp not in _source_digests:
        h = hashlib.sha256()
        for path in paths:
            h.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes() + b"\0")
        _source_digests[stamp] = h.digest()
    return _source_digests[stamp]


@functools.lru_cache(maxsize=1)
def _versions() -> bytes:
    """The libraries' versions and Python's (fixed for a process)."""
    out = []
    for name in _VERSIONED:
        try:
            out.append(f"{name}={importlib.metadata.version(name)}")
        except importlib.metadata.PackageNotFoundError:
            out.append(f"{name}=?")
    return "\0".join([*out, sys.version]).encode()


def _code_digest() -> bytes:
    """SHA-256 of bcmocap's source, the libraries' versions, Python's, and JAX's and equinox's settings that
    change a traced program."""
    h = hashlib.sha256(_source_digest() + _versions())
    h.update(f"\0{os.environ.get('EQX_ON_ERROR', '')}\0".encode())
    h.update(repr(sorted(jax.config.values.items())).encode())  # x64, matmul precision, dtype promotion, ...
    return h.digest()


def program_key(static, dynamic) -> str | None:
    """File stem of the program for ``static`` and ``dynamic`` (the two parts of :func:`equinox.partition`), or None
    when the static part refers to code outside the known packages (or cannot be pickled). The dynamic part
    counts by where its arrays are and their shapes, dtypes and weak types (a field holding an array and one
    holding None look alike in the static part)."""
    marked = jax.tree.map(lambda a: ("array", tuple(a.shape), str(a.dtype), bool(getattr(a, "weak_type", False))),
                          dynamic)
    buffer = io.BytesIO()
    try:
        _KeyPickler(buffer, protocol=5).dump((static, marked))
    except Exception:  # _UnknownCode, or anything that cannot be pickled: no key, the program is traced
        return None
    h = hashlib.sha256(_code_digest())
    h.update(f"{jax.default_backend()}\0".encode())
    h.update(buffer.getvalue())
    return h.hexdigest()


def _folder() -> Path | None:
    cache = jax.config.jax_compilation_cache_dir
    return Path(cache) / _FOLDER if cache else None


def cached_call(fn: Callable, *args):
    """``fn(*args)`` like :func:`equinox.filter_jit` (arrays traced, the rest static), through a program stored
    beside JAX's persistent compilation cache when that cache is on (:mod:`bcmocap.compilation_cache`)
    and the program can be stored; otherwise through ``eqx.filter_jit(fn)``. ``fn`` must be a module-level
    function (its identity is part of the key through the static part)."""
    folder = _folder()
    dynamic, static = eqx.partition((fn, args), eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    key = program_key(static, dynamic) if folder is not None else None
    if key is None or key in _not_storable:
        return _jitted(fn)(*args)
    program = _loaded.get(key)
    if program is None:
        program = _load(folder / f"{key}.bin")
        if program is _DAMAGED:
            print(f"note: dropped the damaged stored program {folder / key}.bin; it is traced again", file=sys.stderr)
            (folder / f"{key}.bin").unlink(missing_ok=True)
            program = None
    if program is None:
        program = _export(fn, static, treedef, leaves, folder / f"{key}.bin")
        if program is None:
            _not_storable.add(key)
            return _jitted(fn)(*args)
    flat_out, out_treedef = program
    try:
        out = flat_out(*leaves)
    except Exception:  # e.g. a stored program this JAX cannot compile: forget it, trace as without the cache
        _loaded.pop(key, None)
        _not_storable.add(key)
        (folder / f"{key}.bin").unlink(missing_ok=True)
        return _jitted(fn)(*args)
    _loaded[key] = program
    return jax.tree.unflatten(out_treedef, out)


@functools.lru_cache(maxsize=None)
def _jitted(fn: Callable) -> Callable:
    return eqx.filter_jit(fn)


_DAMAGED = object()  # what _load returns for a file that exists but cannot be used


def is_whole(path: str | os.PathLike) -> bool:
    """Whether the stored program at ``path`` checks against its SHA-256 and deserialises."""
    return _load(Path(path)) not in (None, _DAMAGED)


def _load(path: Path):
    """The stored program at ``path`` as (callable on flat arrays, output treedef); None when there is no file,
    ``_DAMAGED`` when it does not check against its SHA-256 or cannot be deserialised."""
    from jax import export

    try:
        stored = path.read_bytes()
    except OSError:
        return None
    try:
        first = stored.index(b"\n")
        body = stored[first + 1:]
        if stored[:len(_MAGIC)] != _MAGIC or stored[len(_MAGIC):first].decode() != hashlib.sha256(body).hexdigest():
            return _DAMAGED
        split = body.index(b"\n")
        out_treedef = jax.tree.structure(pickle.loads(bytes.fromhex(body[:split].decode())))
        exported = export.deserialize(bytearray(body[split + 1:]))
    except Exception:  # truncated, overwritten, or from an incompatible writer: trace again
        return _DAMAGED
    return jax.jit(exported.call), out_treedef


def _export(fn: Callable, static, treedef, leaves, path: Path):
    """Trace ``fn`` at these arguments, store the program at ``path``; (callable, output treedef), or None when
    it cannot be exported (then nothing is stored)."""
    from jax import export

    outputs = {}

    def flat(*array_leaves):
        function, args = eqx.combine(jax.tree.unflatten(treedef, array_leaves), static)
        out_leaves, outputs["treedef"] = jax.tree.flatten(function(*args))
        return out_leaves

    try:
        exported = export.export(jax.jit(flat))(*leaves)
        blob = exported.serialize()
        out_treedef = outputs["treedef"]  # stored as the outputs with 0 for every array
        header = pickle.dumps(jax.tree.unflatten(out_treedef, [0] * out_treedef.num_leaves), protocol=5).hex().encode()
    except Exception:  # a host callback, an effect or an output that cannot be pickled
        return None
    try:
        body = header + b"\n" + bytes(blob)
        with atomic_path(path) as tmp:
            tmp.write_bytes(_MAGIC + hashlib.sha256(body).hexdigest().encode() + b"\n" + body)
    except OSError:
        pass  # a read-only cache still gives this process the program
    return jax.jit(exported.call), out_treedef
