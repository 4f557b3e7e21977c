"""JAX's persistent compilation cache, turned on by the commands, benchmarks and examples, and checked for damage.

JAX writes a cache entry in place (not through a temporary file), so a process killed while writing one leaves
a truncated entry; JAX then warns and compiles again on every later run, and never replaces it (an existing key
is never rewritten). :func:`check_compilation_cache` finds such entries when the cache is turned on, drops them
(they are compiled and written again when next needed) and says so in one note:

- an entry not seen before must decompress whole (zstd or zlib, as JAX wrote it) to at least the 4 bytes of
  compilation time JAX puts before the executable; a truncated, emptied or overwritten entry does not;
- an entry seen before must still have the SHA-256 recorded then (``bcmocap_verified.json`` in the cache):
  JAX never rewrites a key, so a changed entry is a damaged one. Entries whose size and time are unchanged
  are not read again, so the check costs milliseconds on a warm cache.

Entries younger than :data:`SETTLING_SECONDS` are left alone: another process may be writing them.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from .atomic import write_json_atomic

#: Seconds a compilation must take to be written to the cache (reading is not affected). A host process that must
#: not serialize executables raises it: the test suite's long-lived workers, where XLA's serialization of an
#: executable threw a C++ exception whose unwinding faulted (``bcmocap.native_crashes``).
MIN_COMPILE_SECONDS = 0.5


#: An entry written less than this many seconds ago may still be being written by another process: not checked.
SETTLING_SECONDS = 5.0
#: The record of checked entries, in the cache folder: name → [size, mtime_ns, SHA-256].
VERIFIED = "bcmocap_verified.json"
_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_TIME_BYTES = 4  # JAX's entry: compilation time (big-endian int32), then the serialized executable


@dataclass
class CacheCheck:
    """What :func:`check_compilation_cache` found: entries checked now, trusted from the record, dropped."""

    folder: Path
    checked: int = 0
    trusted: int = 0
    dropped: list[str] = field(default_factory=list)

    def note(self) -> str | None:
        """One line for the user when entries were dropped, else None."""
        if not self.dropped:
            return None
        return (f"note: dropped {len(self.dropped)} damaged entr{'y' if len(self.dropped) == 1 else 'ies'} of the "
                f"compilation cache {self.folder} ({', '.join(sorted(self.dropped)[:3])}"
                f"{', ...' if len(self.dropped) > 3 else ''}); they are compiled again when needed")


def entry_decodes(blob: bytes) -> bool:
    """Whether a JAX cache entry decompresses whole to at least its compilation-time header."""
    try:
        if blob[:4] == _ZSTD_MAGIC:
            import zstandard

            data = zstandard.ZstdDecompressor().decompress(blob)
        else:
            data = zlib.decompress(blob)
    except ImportError:  # a zstd entry without the zstandard package: JAX could not read it either
        return True
    except Exception:  # zstandard.ZstdError, zlib.error: truncated or not an entry
        return False
    return len(data) > _TIME_BYTES


def check_compilation_cache(folder: str | os.PathLike, now: float | None = None) -> CacheCheck:
    """Drop the damaged entries of JAX's compilation cache in ``folder`` (see the module's docstring) and update
    its record of checked entries. Never raises for a cache it cannot read or write (the check is then skipped
    for the entries concerned)."""
    folder = Path(folder)
    result = CacheCheck(folder)
    now = time.time() if now is None else now
    try:
        record = json.loads((folder / VERIFIED).read_text())
        if not isinstance(record, dict):
            record = {}
    except (OSError, ValueError):
        record = {}
    updated: dict[str, list] = {}
    try:
        entries = sorted(p for p in folder.iterdir() if p.name.endswith("-cache") and p.is_file())
    except OSError:
        return result
    for path in entries:
        try:
            stat = path.stat()
        except OSError:
            continue
        if now - stat.st_mtime < SETTLING_SECONDS:
            continue
        known = record.get(path.name)
        stamp = [stat.st_size, stat.st_mtime_ns]
        if isinstance(known, list) and len(known) == 3 and known[:2] == stamp:
            updated[path.name] = known
            result.trusted += 1
            continue
        try:
            blob = path.read_bytes()
        except OSError:
            continue
        result.checked += 1
        digest = hashlib.sha256(blob).hexdigest()
        recorded = known[2] if isinstance(known, list) and len(known) == 3 else None
        if (recorded is not None and recorded != digest) or not entry_decodes(blob):
            try:
                path.unlink()
                result.dropped.append(path.name)
            except OSError:
                pass
            continue
        updated[path.name] = [*stamp, digest]
    if updated != record:
        try:
            write_json_atomic(folder / VERIFIED, updated)
        except OSError:
            pass
    return result


def enable_compilation_cache() -> None:
    """Persist XLA compilations across runs (``BCMOCAP_CACHE_DIR``, default ``~/.cache/bcmocap/jax``), after
    dropping the cache's damaged entries (:func:`check_compilation_cache`; a note on stderr when there were)."""
    cache = os.environ.get("BCMOCAP_CACHE_DIR", str(Path.home() / ".cache" / "bcmocap" / "jax"))
    try:
        Path(cache).mkdir(parents=True, exist_ok=True)
    except OSError:
        return
    note = check_compilation_cache(cache).note()
    if note:
        print(note, file=sys.stderr)
    import jax

    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)


def memory_mappings() -> tuple[int, int] | None:
    """``(mappings this process has, the kernel's limit vm.max_map_count)``, or None where /proc does not say."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            count = sum(1 for _ in maps)
        with open("/proc/sys/vm/max_map_count") as limit:
            return count, int(limit.read())
    except (OSError, ValueError):
        return None


def release_compiled_programs(share: float = 0.4) -> bool:
    """Free JAX's compiled programs when this process's memory mappings pass ``share`` of the kernel's limit.

    Every compiled XLA:CPU program holds its own memory mappings (about 18 for a small one) for as long as a jitted
    function's cache keeps it, and a process that compiles thousands of them (a batch of captures, a test worker)
    reaches ``vm.max_map_count`` (65530 by default): the next ``mmap`` fails inside XLA and the process aborts or
    crashes. Called between captures and between test files; the programs are compiled again when next used (or
    read from the persistent cache). Returns whether it freed them.
    """
    mappings = memory_mappings()
    if mappings is None or mappings[0] < share * mappings[1]:
        return False
    import gc

    import jax

    jax.clear_caches()
    gc.collect()
    return True
