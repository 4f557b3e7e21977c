"""The public C3D files of the real-file markers benchmark (issue 46): where each comes from, its SHA-256, its terms.

``benchmarks/markers_real.py`` reads the files of ``../shared/data/c3d`` (with their terms there) and these, which
are not redistributed here: each is fetched from its public repository at a pinned commit and checked against its
SHA-256, or copied from a folder that already holds them (``--from``). Their terms are in
``benchmarks/data/c3d_licences/`` (one file per source; some sources give none, and say so).

    python benchmarks/c3d_files.py --out ~/.cache/bcmocap/c3d [--from DIR]

The set: the full-body trials of a person moving that these sources offer and ``bcmocap.io.read_c3d`` reads
(c3d.org's Motion Analysis Cortex and Vicon samples; numediart's Qualisys rolling and its copies of CMU and
HDM05 trials; kineticstoolkit's tennis serve; pyCGM's and gaitalytics' Plug-in Gait walks). Left out, and why:
static or near-static trials (a calibration pose, NexGen's test1: no joint moves, which Kirk's method needs);
lower-body and trunk-only sets (c3d.org's gait-raw, BTS, OpenSim's walks, the treadmill set); two-person files (ART,
kineticstoolkit's copied second player); a golf swing whose club carries markers; a file derived from another by
deleting samples; and four files the reader refuses: c3d.org's Phoenix dance and BTK's OptiTrack mocap36 (their
parameter sections are damaged, which can hang or crash ezc3d; c3d.org says so of the former), c3d.org's
PhaseSpace sample (no POINT parameters at all) and its EVaRT walk (its header's analog frame size, 28 × 17, is not
its parameters' 28 × 16, and read by the parameters every frame after the first is garbled).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import shutil
import sys
import urllib.parse
import urllib.request
from pathlib import Path

LICENCES = Path(__file__).resolve().parent / "data" / "c3d_licences"


@dataclasses.dataclass(frozen=True)
class C3DFile:
    name: str  # the file's name here: SOURCE_original-name.c3d
    repo: str  # GitHub owner/name
    commit: str
    path: str  # in the repository
    sha256: str
    licence: str  # file in LICENCES
    what: str  # system, lab, motion, marker set, rate, gaps

    @property
    def url(self) -> str:
        return f"https://raw.githubusercontent.com/{self.repo}/{self.commit}/{urllib.parse.quote(self.path)}"


FILES = (
    C3DFile("c3dorg_sample00_MAC_Walk1.c3d", "biomechanics-foundation/c3dio", "7950807d12f78a63837d84cc316ccbcf64b48d30",
            "tests/c3d_org_samples/sample_00/Motion Analysis Corporation/Walk1.c3d",
            "f04574a82cca7bb43f340329a6e4c53eeaf6e2136482d8860d1de614a8c17db2", "c3dorg.txt",
            "Motion Analysis (Cortex), walk, Helen Hayes + arms, 60 Hz; 16 % missing, virtual points"),
    C3DFile("c3dorg_sample00_MAC_Sample_Jump2.c3d", "biomechanics-foundation/c3dio", "7950807d12f78a63837d84cc316ccbcf64b48d30",
            "tests/c3d_org_samples/sample_00/Motion Analysis Corporation/Sample_Jump2.c3d",
            "1665d2463cc72a8f7308f12cea5e64d16152dcabe4b6ce8fa9f6e49962e2e3bb", "c3dorg.txt",
            "Motion Analysis (Cortex), vertical jump, Helen Hayes + arms + head, 120 Hz"),
    C3DFile("c3dorg_sample32_vicon_zerowire.c3d", "biomechanics-foundation/c3dio", "7950807d12f78a63837d84cc316ccbcf64b48d30",
            "tests/c3d_org_samples/sample_32/vicon_zerowire.c3d",
            "d1eb8b4e7ae0a123058c936c7da06663c44c7c25b16052c8e82dcca3f4fe1011", "c3dorg.txt",
            "Vicon, walk, Plug-in Gait + 16 unlabelled, 100 Hz; a 34-frame gap"),
    C3DFile("MocapRecovery_03_rolling.c3d", "numediart/MocapRecovery", "8b185712b1015cd8bf871ee1fd3051fac2503bfc",
            "data/03_rolling.c3d",
            "9b34554acbacde7afbc6346f36ca83df3a4a523483d582ae2c037e1554277437", "MocapRecovery.txt",
            "Qualisys (numediart), rolling on the floor, 68 markers, 175 Hz; gaps up to 3.3 s"),
    C3DFile("MocapRecovery_CMU_135_02.c3d", "numediart/MocapRecovery", "8b185712b1015cd8bf871ee1fd3051fac2503bfc",
            "data/135_02.c3d",
            "8a86b00b2b349a78178693ab9056eb3f2238ca029ff14e9f8fb7ae2b6c10bbd2", "MocapRecovery.txt",
            "Vicon (CMU 135_02, martial arts), 41 markers, 120 Hz, 43 s"),
    C3DFile("MocapRecovery_HDM05_HDM_mm_01-02_03_120.c3d", "numediart/MocapRecovery", "8b185712b1015cd8bf871ee1fd3051fac2503bfc",
            "data/HDM_mm_01-02_03_120.c3d",
            "622b6cba680fb5fe5b38b8d6cb27c88de31b3027584ab8792428319d269d9609", "MocapRecovery.txt",
            "Vicon (HDM05, actor mm), 41 markers + 3 unlabelled, 120 Hz"),
    C3DFile("ktk_kinematics_tennis_serve.c3d", "kineticstoolkit/kineticstoolkit", "169a99d7998cbb7c06548487da030ca64b99f90f",
            "data/kinematics_tennis_serve.c3d",
            "c03d21bf53a8d09a567f0b26fdc76414afd29b484554bf94e68309632312ff7d", "ktk.txt",
            "Vicon (UCL), tennis serve, Plug-in Gait 39, 50 Hz, metres"),
    C3DFile("pyCGM_Movement_trial.c3d", "cadop/pyCGM", "1750a62ccda8c60171ebe3d45f929c96e00a8300",
            "SampleData/Test_Files/Movement_trial.c3d",
            "c041153004ad4f92dfd86d92d5ce505194f5121e690af7b03267aa83fbb1bd0e", "pyCGM.txt",
            "Vicon Nexus (pyCGM), walk, Plug-in Gait 39 + 42 unlabelled, 120 Hz; gaps to 107 frames"),
    C3DFile("gaitalytics_test_small.c3d", "DART-Lab-LLUI/python-gaitalytics", "4d6823a8fe58525ef474b9283da697d3fe46ae65",
            "tests/full/data/test_small.c3d",
            "0c3e446ea03ed8fc50de2b0f7e8a7fbadad1597ef6dabf5e374d60ec3c0b1e97", "gaitalytics.txt",
            "Vicon Nexus (Lucerne), walk, Plug-in Gait 33, 100 Hz"),
)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def ensure_files(folder: Path, source: Path | None = None, log=print) -> list[Path]:
    """Every file of :data:`FILES` in ``folder``: kept if there with the right SHA-256, else copied from ``source``
    or fetched from its repository; each checked against its SHA-256.

    Raises:
        ValueError: one line naming the file that could not be had or whose content differs.
    """
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for f in FILES:
        target = folder / f.name
        if not (target.is_file() and _sha256(target) == f.sha256):
            partial = target.with_suffix(".part")
            if source is not None and (source / f.name).is_file():
                shutil.copyfile(source / f.name, partial)
            else:
                log(f"fetching {f.name} from {f.repo}")
                try:
                    with urllib.request.urlopen(f.url, timeout=60) as response, partial.open("wb") as sink:
                        shutil.copyfileobj(response, sink)
                except OSError as exc:
                    partial.unlink(missing_ok=True)
                    raise ValueError(f"{f.name}: cannot fetch {f.url} ({exc}); copy it into {folder} or give --from") from None
            if _sha256(partial) != f.sha256:
                partial.unlink()
                raise ValueError(f"{f.name}: its content differs from the pinned file (SHA-256 {f.sha256[:12]}…)")
            partial.replace(target)
        out.append(target)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder to hold the files")
    parser.add_argument("--from", dest="source", type=Path, help="a folder that already holds them (copied, checked)")
    args = parser.parse_args(argv)
    try:
        paths = ensure_files(args.out, args.source)
    except ValueError as exc:
        print(f"c3d_files: {exc}", file=sys.stderr)
        return 1
    print(f"{len(paths)} files in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
