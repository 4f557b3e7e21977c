"""What a marker's name says about where it sits: a side and a body region, read from the names marker sets use.

Real C3D files name their markers after a marker set: Vicon's Plug-in Gait and the CMU/HDM05 set (``LTHI``,
``RKNE``, ``LASI``, ``C7``, ``LWRA``…), Motion Analysis' Helen Hayes (``RSHA``, ``L.TO``, ``THEA``), and anatomical
landmark sets after ISB/CAST (``L_FTC``, ``R_FLE``, ``L_FAL``, ``CV7``, ``L_HLE``…). A name is a hint, never a
label: the pipeline uses it as a soft prior (markers whose names put them on bones no joint separates from each other
are more likely one segment; segments whose names no joint of the body joins are less likely joined), and the motion
decides (:class:`~bcmocap.markers.pipeline.MarkerOptions.label_prior`).

A region is a bone (``pelvis``, ``trunk``, ``head``, ``thigh``, ``shank``, ``foot``, ``upper_arm``, ``forearm``,
``hand``) or a joint a marker sits on, between two bones (``knee``, ``ankle``, ``elbow``, ``wrist``, ``shoulder``).
A side is ``"L"``, ``"R"`` or None (on the midline, or a head or trunk marker whose side no joint separates).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence

import numpy as np

__all__ = ["MarkerHint", "group_label_penalties", "informative", "marker_hints", "marker_label_weights"]

#: Marker codes (the name without its side) of each region; a trailing number is dropped (``TH1``, ``SK2``).
_CODES = {
    "pelvis": ("ASI", "PSI", "IAS", "IPS", "FWT", "BWT", "SACR", "SACRUM", "WT"),
    "trunk": ("C7", "CV7", "T10", "TV10", "TV8", "T8", "CLAV", "STRN", "SNJ", "SXS", "BAK", "BAC", "SCAP", "OFF"),
    "head": ("FHD", "BHD", "HDF", "HDB", "HEA", "THEA", "FHEA", "RHEA", "HEAD"),
    "shoulder": ("SHO", "SAJ", "AC", "ACR"),
    "thigh": ("THI", "FTC", "TH", "THIGH"),
    "knee": ("KNE", "FLE", "FME", "KNEE"),
    "shank": ("TIB", "SHN", "SHA", "SH", "FAX", "TTC", "SK", "SHANK"),
    "ankle": ("ANK", "FAL", "TAM", "ANKLE"),
    "foot": ("HEE", "TOE", "TO", "MT5", "MT1", "FCC", "FM1", "FM2", "FM5", "HEEL"),
    "upper_arm": ("UPA", "UA", "HUM"),
    "elbow": ("ELB", "HLE", "HME", "ELBOW"),
    "forearm": ("FRM", "FA", "FOREARM"),
    "wrist": ("WRA", "WRB", "WRI", "RSP", "USP", "WRIST"),
    "hand": ("FIN", "HA", "HM1", "HM2", "HM5", "HL5", "HAND"),
}
_REGION_OF = {code: region for region, codes in _CODES.items() for code in codes}
#: Regions whose markers may carry a side and still lie on one rigid bone with the other side's (a pelvis' ASIs).
_AXIAL = frozenset(("pelvis", "trunk", "head", "shoulder"))
#: The two bones a joint marker sits between.
_JOINT_BONES = {"knee": ("thigh", "shank"), "ankle": ("shank", "foot"), "elbow": ("upper_arm", "forearm"),
                "wrist": ("forearm", "hand"), "shoulder": ("trunk", "upper_arm")}
#: The bones a joint of the body joins (a side's limb bones with the same side's).
_JOINED = {frozenset(pair) for pair in (("pelvis", "thigh"), ("pelvis", "trunk"), ("trunk", "head"),
                                         ("trunk", "upper_arm"), ("thigh", "shank"), ("shank", "foot"),
                                         ("upper_arm", "forearm"), ("forearm", "hand"))}
_LIMB_OF = {**dict.fromkeys(("thigh", "knee", "shank", "ankle", "foot"), "leg"),
            **dict.fromkeys(("upper_arm", "elbow", "forearm", "wrist", "hand"), "arm"), "head": "head"}
_NAME = re.compile(r"^(?P<side>[LR])?[_\-. ]?(?P<code>[A-Z]+\d*)$")


@dataclasses.dataclass(frozen=True)
class MarkerHint:
    """Where a marker's name puts it: ``side`` ``"L"``, ``"R"`` or None; ``region`` (module docstring)."""

    side: str | None
    region: str

    def bones(self) -> tuple[str, ...]:
        """The bones the marker may lie on: its region's, or the two a joint marker sits between."""
        return _JOINT_BONES.get(self.region, (self.region,))

    def limb(self) -> str | None:
        """``"leg"``, ``"arm"`` or ``"head"`` where the marker is on one (None: the pelvis, the thorax, a shoulder)."""
        return _LIMB_OF.get(self.region)


def _parse(name: str) -> MarkerHint | None:
    """One name without its subject prefix and copy suffix (``Male:LTHI``, ``RKNE#2``), else None."""
    m = _NAME.match(name)
    if m is None:
        return None
    side, code = m.group("side"), m.group("code")
    for candidate in (code, code.rstrip("0123456789")):
        region = _REGION_OF.get(candidate)
        if region is not None:
            if side is None and region not in _AXIAL:
                return None  # a limb marker without a side says too little
            return MarkerHint(None if region in ("head", "trunk") else side, region)  # RHEA: the rear of the head
    return None


def _stem(label: str) -> str:
    return re.sub(r"#\d+$", "", label.split(":")[-1].strip()).strip().upper()


def marker_hints(labels: Sequence[str]) -> list[MarkerHint | None]:
    """Each label's hint (None where its name says nothing known). Where at least 80 % of the names that start
    with a letter share one extra leading letter before their side (a subject's initial: ``LLTHI``, ``LRKNE``),
    and fewer than half parse as they are, that letter is dropped from those names first."""
    stems = [_stem(label) for label in labels]
    hints = [_parse(s) for s in stems]
    initials = [s[0] for s in stems if s[:1].isalpha()]
    if initials and sum(h is not None for h in hints) < len(stems) / 2:
        letter = max(set(initials), key=initials.count)
        if initials.count(letter) >= 0.8 * len(initials):
            shifted = [_parse(s[1:]) if s[:1] == letter else h for s, h in zip(stems, hints)]
            if sum(h is not None for h in shifted) > sum(h is not None for h in hints):
                hints = shifted
    return hints


def _one_bone(a: MarkerHint, b: MarkerHint) -> bool:
    """Whether the two markers may lie on one rigid bone: a bone both may lie on (the pelvis, the thorax and the
    head are three), on one side unless it is an axial bone."""
    shared = set(a.bones()) & set(b.bones())
    if not shared:
        return False
    if shared & _AXIAL:  # the pelvis, the thorax with both shoulders' markers, the head
        return True
    return a.side is None or b.side is None or a.side == b.side


def marker_label_weights(hints: Sequence[MarkerHint | None], factor: float) -> np.ndarray:
    """``(M, M)`` multipliers of the segmentation's affinities: ``1 / factor`` between two markers whose names put
    them on bones no one rigid segment holds (a thigh's and a shin's, the left and the right thigh's), 1 elsewhere
    (and wherever a name says nothing)."""
    m = len(hints)
    out = np.ones((m, m))
    if not factor:
        return out
    for i in range(m):
        for j in range(i + 1, m):
            a, b = hints[i], hints[j]
            if a is not None and b is not None and not _one_bone(a, b):
                out[i, j] = out[j, i] = 1.0 / factor
    return out


def _group_bones(hints: Sequence[MarkerHint]) -> tuple[set[str], set[str]]:
    """The bones a segment of these markers may be (those every marker may lie on, else any marker's) and the
    sides its limb markers name."""
    each = [set(h.bones()) for h in hints]
    common = set.intersection(*each)
    return (common or set.union(*each)), {h.side for h in hints if h.side is not None and h.region not in _AXIAL}


def _joinable(a: tuple[set[str], set[str]], b: tuple[set[str], set[str]]) -> bool:
    """Whether a joint of the body may join a segment of bones and sides ``a`` to one of ``b``."""
    for x in a[0]:
        for y in b[0]:
            if x == y or frozenset((x, y)) in _JOINED:
                if {x, y} & _AXIAL or not a[1] or not b[1] or a[1] & b[1]:
                    return True
    return False


def group_label_penalties(hints: Sequence[MarkerHint | None], marker_group: np.ndarray, num_groups: int,
                          factor: float) -> np.ndarray:
    """``(G, G)`` multipliers of the joint costs: ``factor`` between two segments no joint of the body joins by
    their markers' names (a foot's and the pelvis', a left shin's and a right thigh's; a segment of a knee and a
    shin marker is a shin), 1 elsewhere (and for a segment whose markers' names say nothing)."""
    out = np.ones((num_groups, num_groups))
    if not factor:
        return out
    named = [[hints[k] for k in np.flatnonzero(marker_group == g) if hints[k] is not None] for g in range(num_groups)]
    bones = [_group_bones(n) if n else None for n in named]
    for g in range(num_groups):
        for h in range(g + 1, num_groups):
            if bones[g] is not None and bones[h] is not None and not _joinable(bones[g], bones[h]):
                out[g, h] = out[h, g] = factor
    return out


def informative(hints: Sequence[MarkerHint | None]) -> bool:
    """Whether the names say enough to use: at least 10 name a region, on both sides of the body (unnamed
    trajectories, ``*12``, are common beside a named set)."""
    known = [h for h in hints if h is not None]
    return len(known) >= 10 and {"L", "R"} <= {h.side for h in known}
