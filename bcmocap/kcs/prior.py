"""The initial configuration of a reconstruction from a pool of motions, kept in a file keyed by the pool.

:func:`~bcmocap.kcs.chain_space.mean_pose` aligns every frame of its pool (generalised Procrustes, four rounds over
all frames): seconds for a pool of a few thousand frames, and a pool of motion-capture trials is read from disk first.
:func:`pool_mean_pose` computes it once per pool and keeps it as ``kcs-prior-<key>.npz`` in a folder (by default the
compilation cache's parent, ``~/.cache/bcmocap``, or ``$BCMOCAP_CACHE_DIR/..``), where ``key`` hashes the chain (names,
parents, extra links), the pool's arrays (names, shapes, bytes) and the settings: another pool, a changed trial or
another chain is another file; a damaged file is computed again. (The shape basis ``S`` of Algorithm 1 is each
sequence's own, from its 2-D joints; only the mean pose comes from the pool.)
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ..atomic import write_npz_atomic
from .chain_space import KinematicChainSpace, mean_pose

__all__ = ["pool_key", "pool_mean_pose", "prior_folder"]

_VERSION = 1  # bump when mean_pose's result changes for the same pool


def prior_folder() -> Path:
    """Where priors are kept: ``$BCMOCAP_CACHE_DIR/..`` if set, else ``~/.cache/bcmocap``."""
    cache = os.environ.get("BCMOCAP_CACHE_DIR")
    return Path(cache).parent if cache else Path.home() / ".cache" / "bcmocap"


def pool_key(pool: Mapping[str, np.ndarray], chain: KinematicChainSpace, max_frames: int | None) -> str:
    """A hex digest of the chain, the pool (each trial's name, shape and float64 bytes) and the settings."""
    digest = hashlib.sha256()
    digest.update(repr((_VERSION, tuple(chain.names), tuple(chain.parents), tuple(chain.extra_links), max_frames)).encode())
    for name in pool:  # in the pool's order: the mean pose takes the orientation of its first frame
        x = np.ascontiguousarray(pool[name], dtype=np.float64)
        digest.update(repr((name, x.shape)).encode())
        digest.update(x.tobytes())
    return digest.hexdigest()


def pool_mean_pose(pool: Mapping[str, np.ndarray], chain: KinematicChainSpace, *, max_frames: int | None = 300,
                   folder: str | os.PathLike | None = None) -> np.ndarray:
    """The mean pose ``(J, 3)`` of a pool of trials (name → ``(F, J, 3)`` joints, m), each evenly subsampled to at most
    ``max_frames`` frames so that no trial dominates (None: all frames), from its file in ``folder`` (default
    :func:`prior_folder`) or computed and written there (module docstring)."""
    if not pool:
        raise ValueError("pool_mean_pose: the pool holds no trial")
    key = pool_key(pool, chain, max_frames)
    path = Path(folder if folder is not None else prior_folder()) / f"kcs-prior-{key[:24]}.npz"
    try:
        with np.load(path) as data:
            if str(data["key"]) == key and data["mean_pose"].shape == (chain.num_joints, 3):
                return np.array(data["mean_pose"], np.float64)
    except (OSError, KeyError, ValueError, EOFError):
        pass  # none yet, or not readable: computed again
    trials = [np.asarray(pool[name], np.float64) for name in pool]
    if max_frames is not None:
        trials = [x[np.linspace(0, len(x) - 1, min(len(x), max_frames)).astype(int)] for x in trials]
    pose = mean_pose(trials, chain)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_npz_atomic(path, {"key": np.array(key), "mean_pose": pose})
    except OSError:
        pass  # a read-only cache: the pose is still right
    return pose
