"""Which part of a human body each recovered segment is: the tree matched against a human template.

Kirk et al.'s pipeline finds rigid marker groups and the tree that connects them, but nothing in it knows what a
body is. This module labels the recovered tree against a human template, from the tree's shape, the segments'
rigid lengths and the motion; marker names (which differ between labs and are absent from unlabelled files) only
weigh in where the caller passes what they say (``hints``: a soft prior on which chain is which limb, and the sides
where they tell them apart; :mod:`~bcmocap.markers.label_hints`):

- **Template.** A core (pelvis, spine, thorax; one rigid segment where they did not move relative to each other)
  with five limbs hanging from it: two legs from the pelvis (thigh, shin, foot, toes), two arms from the thorax
  (shoulder, upper arm, forearm, hand) and the head (neck, head). A limb may have fewer segments than that (a
  foot that moved with its shin is one segment with it; an arm whose elbow never bent is one rigid segment), but
  a leg is never one segment from hip to foot.
- **Limbs.** The tree's *leaf chains*: from each leaf inward, up to the first segment with three or more
  neighbours (its attachment). Leaves of less than :data:`TWIG_M` reach that hang from such a segment (a single
  marker given its own segment) are set aside first, as *extra*. The segments no chain holds are the core.
- **Lengths.** Each segment's length (joint to joint, the last joint to its farthest marker) and a chain's reach
  (their sum), medians over the frames of rigid distances, so any posture gives them; all over the body's size
  (:func:`_body_size`).
- **Assignment.** Every assignment of chains to two legs, two arms and a head (a limb may stay empty) is scored
  (``_Tree.cost``, negative log-plausibilities): each limb's reach and each segment's length against de Leva's
  proportions (:data:`_LENGTHS`), the limbs of a pair alike and attached to one core segment, the trunk (hips to
  shoulders) about 0.3 of the body, legs hanging away from the thorax (along the body's own axis, hips to
  shoulders, so a subject lying or rolling on the floor is no different), the head above the shoulders and near
  the midline, and arms and head no nearer the pelvis than the legs. The best assignment is kept, and each
  segment's confidence is how much better it is than the best one that labels that segment otherwise
  (``1 - exp(-Δcost)``).
- **Left and right.** The body's left from its knees, which flex backward (the thigh's direction crossed with
  the shin's points to the body's left, on either leg), and from its feet, which point forward (the shin's
  upward direction crossed with the ankle-to-foot direction points left); where the legs show neither, from the
  elbows, which flex forward (the same cross product points right). A limb pair is left and right by which side
  of that direction its joints are on in most frames.

:func:`label_anatomy` returns an :class:`Anatomy`: a label and a confidence per segment, and the verdict
(``human``, and which limbs are wrong, each with a one-line reason and its cause), and
:func:`template_penalties` turns the labels, and :func:`region_penalties` the body regions that
:func:`body_regions` reads from where the markers are, into a prior on the tree's joints (used by
:func:`~bcmocap.markers.fit_marker_skeleton` where a tree is not a body).
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

__all__ = ["Anatomy", "CAUSES", "LIMBS", "TWIG_M", "body_regions", "label_anatomy", "region_penalties",
           "template_penalties"]

LIMBS = ("left_leg", "right_leg", "left_arm", "right_arm", "head")
#: What can be wrong with a limb: not found; a leg in one rigid segment; more segments than the limb has; a segment
#: of implausible length; the legs apart in the tree; a "leg" that does not hang down; an arm or head on a pelvis
#: alone; a head among the trunk's segments.
CAUSES = ("missing", "rigid_leg", "too_many", "length", "legs_apart", "not_hanging", "on_pelvis", "head_in_trunk")
#: How a limb of N segments may be named, proximal first; a name ending in "+" holds the parts after it too.
_NAMINGS = {
    "leg": {1: [("leg+",), ("shin+",)], 2: [("thigh", "shin+")], 3: [("thigh", "shin", "foot")],
            4: [("thigh", "shin", "foot", "toes"), ("thigh", "shin", "ankle", "foot")]},
    "arm": {1: [("arm+",), ("forearm+",)], 2: [("upper_arm", "forearm+"), ("arm", "hand")],
            3: [("upper_arm", "forearm", "hand"), ("shoulder", "upper_arm", "forearm+")],
            4: [("shoulder", "upper_arm", "forearm", "hand")]},
    "head": {1: [("head",)], 2: [("neck", "head")]},
}
#: Each segment's length over the body's size (:func:`_body_size`, about its height): joint to joint, or for the
#: last segment of a limb joint to its farthest marker. From de Leva (1996, J Biomech 29:1223): thigh 0.245,
#: shank 0.246, upper arm 0.186, forearm 0.146; the foot, hand and head from the ankle, wrist and neck to the
#: markers that end them (toe, knuckles, a headband's markers at the forehead); "+" with the parts below; an "arm"
#: is the upper arm and forearm together, shoulder to wrist (an elbow that did not bend, its hand apart); an
#: "ankle" is the shank's lower part where its markers there (malleoli, a cluster) moved apart from the upper ones.
_LENGTHS = {"leg+": 0.55, "thigh": 0.245, "shin": 0.246, "shin+": 0.27, "foot": 0.11, "toes": 0.04, "ankle": 0.08,
            "arm+": 0.38, "arm": 0.33, "shoulder": 0.09, "upper_arm": 0.186, "forearm": 0.146, "forearm+": 0.2, "hand": 0.06,
            "neck": 0.06, "head": 0.09}
#: A segment that holds both the legs and the arms is the whole trunk only if its markers spread this far along the
#: body (over its size): the pelvis's alone span about 0.1, the trunk's 0.3 and more.
_TRUNK_EXTENT = 0.2
#: Hips to shoulders (the joints) over the body's size: de Leva's trunk, hip to shoulder joint centres, about 0.3.
_TRUNK = 0.3
_LENGTH_SIGMA = 0.35  # log-normal spread of a segment's length against _LENGTHS (bodies, markers, joint placement)
#: A core segment whose markers lie this far along the body (hips 0, shoulders 1) is a head, not a spine; a head
#: chain's markers lie at least _HEAD_LEVEL (1.15 on the studio's body, 1.4 on HDM05's; a shoulder marker 1.08).
_ABOVE_SHOULDERS, _HEAD_LEVEL = 1.25, 1.1
#: A leaf segment reaching less than this (m) from its joint that hangs from a branching segment is set aside.
TWIG_M = 0.10
#: A limb's reach over the body's size (:func:`_body_size`, about its height): hip to toe (thigh 0.245, shank 0.246,
#: foot), shoulder to fingertips (upper arm 0.186, forearm 0.146, hand 0.108; de Leva 1996, J Biomech 29:1223),
#: neck to the head's markers (a headband's, at the forehead: about 0.09 of the body; CMU 135_02's 8 %).
_LEG_REACH, _ARM_REACH, _HEAD_REACH = 0.58, 0.42, 0.1
_MISSING_LIMB = 12.0  # cost of leaving an arm or a leg without a chain
_MISSING_HEAD = 2.0  # a head may be part of the core (it moved with the thorax) or carry no markers
_EXTRA_CHAIN = 1.0  # a chain left over (a wand, a marker cluster of something held)
_NAMES_DISAGREE = 20.0  # a chain all of whose named markers the names put on another limb (a share: less)


@dataclasses.dataclass(frozen=True)
class Anatomy:
    """A recovered tree labelled against the human template.

    Attributes:
        labels: ``(S,)`` per segment: ``"pelvis"``, ``"spine"``, ``"thorax"``, ``"trunk"`` (pelvis and thorax in one
            segment), ``"neck"``, ``"head"``, ``"left_thigh"``, ``"left_shin"``, ``"left_foot"``, ``"left_toes"``,
            ``"left_shoulder"``, ``"left_upper_arm"``, ``"left_forearm"``, ``"left_hand"``, the same on the right;
            ``"extra"`` for a segment the template has no place for.
        confidence: ``(S,)`` in [0, 1] (module docstring).
        limbs: ``{limb: segment indices, proximal first}`` of each limb found (:data:`LIMBS`).
        human: every arm and leg found, of at least two segments, where a body has it.
        wrong_limbs: ``{limb: reason}`` for each arm or leg that is missing or implausible; empty when human.
        notes: what the verdict does not hinge on (the pelvis and thorax in one segment, no head, extra segments).
        cost: the best assignment's cost (negative log-plausibility; lower is more of a body).
        causes: ``{limb: (kind, segments)}`` for each wrong limb: what is wrong (:data:`CAUSES`) and the segments
            it involves.
    """

    labels: tuple[str, ...]
    confidence: np.ndarray
    limbs: dict
    human: bool
    wrong_limbs: dict
    notes: tuple[str, ...]
    cost: float = 0.0
    causes: dict = dataclasses.field(default_factory=dict)

    def to_dict(self, names) -> dict:
        """``{"human", "wrong_limbs": [...], "reasons": {...}, "notes"}``, the ``"verdict"`` of ``skeleton.json``."""
        return {"human": self.human, "wrong_limbs": list(self.wrong_limbs), "reasons": dict(self.wrong_limbs),
                "limbs": {limb: [names[j] for j in chain] for limb, chain in self.limbs.items()},
                "notes": list(self.notes)}


def _body_size(markers: np.ndarray) -> float:
    """The body's size (m): the median over frames of the largest distance between two of its markers (its height
    standing; a little more with the arms raised)."""
    spans = []
    for frame in markers:
        seen = frame[np.isfinite(frame).all(axis=1)]
        if len(seen) >= 2:
            spans.append(np.sqrt(((seen[:, None] - seen[None]) ** 2).sum(-1).max()))
    return float(np.median(spans)) if spans else 1.0


def _median_distance(a: np.ndarray, b: np.ndarray) -> float:
    d = np.linalg.norm(a - b, axis=-1)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else 0.0


@dataclasses.dataclass(frozen=True)
class _Chain:
    segments: tuple  # proximal (next to the attachment) first
    attachment: int
    reach: float  # m
    lengths: tuple  # m, per segment (module docstring of _LENGTHS)
    start: np.ndarray  # (F, 3) the attachment joint
    end: np.ndarray  # (F, 3) the leaf's farthest marker


class _Tree:
    """The recovered tree with its chains, core and the frames the matching looks at."""

    def __init__(self, parents, joints, markers, marker_segment, hints=None):
        self.parents, self.joints, self.markers, self.marker_segment = parents, joints, markers, marker_segment
        self.size = len(parents)
        self.height = _body_size(markers)
        self._midpoints: dict = {}  # sorted chain indices → (F, 3) (midpoint)
        self._namings: dict = {}  # (kind, chain) → naming
        self.nbrs = [set() for _ in parents]
        for j, p in enumerate(parents):
            if p >= 0:
                self.nbrs[j].add(p)
                self.nbrs[p].add(j)
        self.twigs = self._twigs()
        self.chains = self._chains()
        held = {j for c in self.chains for j in c.segments} | set(self.twigs)
        self.core = [j for j in range(self.size) if j not in held]
        self.hops = self._core_hops()
        self.named = [self._names_say(c, hints) for c in self.chains]
        # what leaving each chain unassigned costs: its names put it on a limb (most of its limb markers' names)
        self.left_over = [_NAMES_DISAGREE * max(kinds.values()) if kinds and max(kinds.values()) > 0.5 else 0.0
                          for kinds, _ in self.named]

    def _names_say(self, chain: _Chain, hints) -> tuple[dict, float]:
        """What the chain's markers' names say (:mod:`~bcmocap.markers.label_hints`): the share of its named limb
        markers on each limb kind, and its side from -1 (right) to 1 (left); ``({}, 0)`` without names, a half on
        each kind where the names give the chain no limb marker."""
        if hints is None:
            return {}, 0.0
        said = [hints[m] for m in np.flatnonzero(np.isin(self.marker_segment, chain.segments))
                if hints[m] is not None and hints[m].limb() is not None]
        if not said:  # among named markers, a chain with no limb's names: as likely no limb as any
            return {"leg": 0.5, "arm": 0.5, "head": 0.5}, 0.0
        kinds = {kind: sum(h.limb() == kind for h in said) / len(said) for kind in ("leg", "arm", "head")}
        return kinds, sum((h.side == "L") - (h.side == "R") for h in said) / len(said)

    def joint(self, a: int, b: int) -> np.ndarray:
        """``(F, 3)`` the joint between neighbours ``a`` and ``b`` (the child's origin)."""
        return self.joints[:, a if self.parents[a] == b else b]

    def centroid(self, j: int) -> np.ndarray:
        """``(F, 3)`` the mean of segment ``j``'s markers."""
        return self.markers[:, self.marker_segment == j].mean(axis=1)

    def far_end(self, j: int, towards: int) -> np.ndarray:
        """``(F, 3)`` the marker of segment ``j`` farthest from its joint with ``towards``."""
        base = self.joint(j, towards)
        own = np.flatnonzero(self.marker_segment == j)
        if not len(own):
            return base
        return self.markers[:, max(own, key=lambda m: _median_distance(self.markers[:, m], base))]

    def _twigs(self) -> list[int]:
        """Leaves reaching less than :data:`TWIG_M` from a branching segment, set aside round by round."""
        twigs: set = set()
        while True:
            live = {j: self.nbrs[j] - twigs for j in range(self.size) if j not in twigs}
            new = [j for j, n in live.items() if len(n) == 1 and len(live[next(iter(n))]) >= 3
                   and _median_distance(self.far_end(j, next(iter(n))), self.joint(j, next(iter(n)))) < TWIG_M]
            if not new:
                return sorted(twigs)
            twigs.update(new)

    def _chains(self) -> list[_Chain]:
        """From each leaf inward, up to the first segment with three or more neighbours (twigs aside)."""
        twigs = set(self.twigs)
        live = {j: self.nbrs[j] - twigs for j in range(self.size) if j not in twigs}
        chains = []
        for leaf in (j for j, n in live.items() if len(n) == 1):
            path, prev, node = [leaf], None, leaf
            while True:
                (nxt,) = [k for k in live[node] if k != prev] or [None]
                if nxt is None or len(live[nxt]) != 2:
                    break
                prev, node = node, nxt
                path.append(node)
            if nxt is None or len(live[nxt]) < 3:
                continue  # a bare path: nothing hangs from a core
            segments = tuple(path[::-1])
            points = [self.joint(segments[0], nxt)] + [self.joint(a, b) for a, b in zip(segments, segments[1:])]
            end = self.far_end(segments[-1], segments[-2] if len(segments) > 1 else nxt)
            points.append(end)
            lengths = tuple(_median_distance(p, q) for p, q in zip(points, points[1:]))
            chains.append(_Chain(segments, nxt, float(sum(lengths)), lengths, points[0], end))
        return chains

    def _core_hops(self) -> dict:
        """``{(a, b): joints between them}`` for every two core segments (breadth-first within the core)."""
        core = set(self.core)
        hops = {}
        for start in core:
            seen, frontier = {start: 0}, [start]
            while frontier:
                following = []
                for j in frontier:
                    for k in self.nbrs[j] & core:
                        if k not in seen:
                            seen[k] = seen[j] + 1
                            following.append(k)
                frontier = following
            hops.update({(start, k): d for k, d in seen.items()})
        return hops

    def hop(self, a: int, b: int) -> int:
        """Joints between two core segments (4 where either is not in the core)."""
        return self.hops.get((a, b), 4)

    def midpoint(self, chains) -> np.ndarray:
        """``(F, 3)`` the mean of the chains' attachment joints (the hips of the legs, the shoulders of the arms),
        computed once per set of chains (the assignments ask for the same sets again and again)."""
        key = tuple(sorted(chains))
        if key not in self._midpoints:
            self._midpoints[key] = np.mean([self.chains[i].start for i in key], axis=0)
        return self._midpoints[key]

    def body_axis(self, legs, arms) -> np.ndarray | None:
        """``(F, 3)`` unit vectors from the hips' midpoint to the shoulders' (None without legs or arms)."""
        if not legs or not arms:
            return None
        axis = self.midpoint(arms) - self.midpoint(legs)
        norm = np.linalg.norm(axis, axis=-1, keepdims=True)
        return np.where(norm > 1e-6, axis / np.maximum(norm, 1e-12), np.nan)

    def trunk(self, legs, arms) -> float:
        """The trunk's length over the body's size: from the hips' midpoint to the shoulders' (the legs' and arms'
        attachment joints), median over frames."""
        return _median_distance(self.midpoint(legs), self.midpoint(arms)) / self.height

    def hanging(self, chain: int, axis: np.ndarray) -> float:
        """Median over frames of the chain's far end's displacement from its attachment joint along ``axis``,
        over its reach (-1: straight down the body axis, +1: up it)."""
        c = self.chains[chain]
        along = np.einsum("fi,fi->f", c.end - c.start, axis) / max(c.reach, 1e-6)
        along = along[np.isfinite(along)]
        return float(np.median(along)) if len(along) else 0.0

    def cost(self, legs, arms, head) -> float:
        """Negative log-plausibility of an assignment of chains (indices) to the legs, arms and head."""
        chains = self.chains
        cost = _MISSING_LIMB * ((2 - len(legs)) + (2 - len(arms))) + _MISSING_HEAD * (1 - len(head))
        cost += _EXTRA_CHAIN * (len(chains) - len(legs) - len(arms) - len(head))
        h = self.height
        cost += sum((np.log(chains[i].reach / h / _LEG_REACH) / 0.15) ** 2 for i in legs)
        cost += sum((np.log(chains[i].reach / h / _ARM_REACH) / 0.25) ** 2 for i in arms)
        cost += sum((np.log(chains[i].reach / h / _HEAD_REACH) / 0.45) ** 2 for i in head)
        for pair in (legs, arms):
            if len(pair) == 2:
                cost += (np.log(chains[pair[0]].reach / chains[pair[1]].reach) / 0.2) ** 2
                cost += self.hop(chains[pair[0]].attachment, chains[pair[1]].attachment)
        for kind, group in (("leg", legs), ("arm", arms), ("head", head)):
            cost += sum(self.naming(kind, i)[0] for i in group)
            # the markers' names (where given) that put a chain on another limb
            cost += sum(_NAMES_DISAGREE * (1.0 - self.named[i][0].get(kind, 1.0)) for i in group)
        assigned = {*legs, *arms, *head}  # and a chain left over that the names put on a limb
        cost += sum(c for i, c in enumerate(self.left_over) if i not in assigned)
        axis = self.body_axis(legs, arms)
        if axis is not None:
            cost += (np.log(max(self.trunk(legs, arms), 1e-3) / _TRUNK) / 0.3) ** 2  # hips to shoulders
            cost += sum(6.0 * max(0.0, self.hanging(i, axis) + 0.3) for i in legs)  # legs hang away from the thorax
            cost += sum(4.0 * max(0.0, -self.hanging(i, axis)) for i in head)  # the head points away from the legs
            cost += sum(20.0 * max(0.0, _HEAD_LEVEL - self.level(chains[i].segments[-1], legs, arms))
                        + 10.0 * max(0.0, self.off_midline(chains[i].segments[-1], legs, arms) - 0.5)
                        for i in head)  # above the shoulders, between them
        if legs:
            pelvis = chains[legs[0]].attachment
            for i in (*arms, *head):  # arms and head attach no nearer the pelvis than the legs do
                nearest = min(self.hop(chains[k].attachment, chains[i].attachment) for k in legs)
                cost += 0.5 * max(0, nearest - self.hop(pelvis, chains[i].attachment))
        return float(cost)

    def extent(self, j: int, axis: np.ndarray) -> float:
        """How far segment ``j``'s markers spread along ``axis`` (median over frames), over the body's size."""
        own = self.markers[:, self.marker_segment == j]
        if not own.shape[1]:
            return 0.0
        along = np.einsum("fmi,fi->fm", own, axis)
        spread = np.nanmax(along, axis=1) - np.nanmin(along, axis=1)
        spread = spread[np.isfinite(spread)]
        return float(np.median(spread)) / self.height if len(spread) else 0.0

    def naming(self, kind: str, chain: int) -> tuple[float, tuple]:
        """The cheapest naming of a chain as a ``kind`` limb (:data:`_NAMINGS`) and its cost: the segments' lengths
        against :data:`_LENGTHS`, or 3 per segment past the template's."""
        if (kind, chain) in self._namings:
            return self._namings[kind, chain]
        self._namings[kind, chain] = self._naming(kind, chain)
        return self._namings[kind, chain]

    def _naming(self, kind: str, chain: int) -> tuple[float, tuple]:
        lengths = self.chains[chain].lengths
        n = len(lengths)
        options = _NAMINGS[kind]
        if n > max(options):
            names = options[max(options)][0]
            return 3.0 * (n - len(names)), names + ("extra",) * (n - len(names))
        return min((sum((np.log(max(length, 1e-3) / self.height / _LENGTHS[name]) / _LENGTH_SIGMA) ** 2
                        for length, name in zip(lengths, names)), names) for names in options[n])

    def assignments(self) -> list[tuple[float, tuple, tuple, tuple]]:
        """Every assignment ``(cost, legs, arms, head)``, cheapest first."""
        out = []
        every = range(len(self.chains))
        for n_legs, n_arms, n_head in itertools.product((2, 1, 0), (2, 1, 0), (1, 0)):
            for legs in itertools.combinations(every, n_legs):
                rest = [i for i in every if i not in legs]
                for arms in itertools.combinations(rest, n_arms):
                    for head in itertools.combinations([i for i in rest if i not in arms], n_head):
                        out.append((self.cost(legs, arms, head), legs, arms, head))
        out.sort(key=lambda row: row[0])
        return out

    def left(self, legs, arms) -> np.ndarray | None:
        """``(F, 3)`` the body's left (its length weighs the frame): knees and feet, else elbows."""
        total, found = np.zeros_like(self.joints[:, 0]), False
        for i in legs:
            c = self.chains[i]
            if len(c.segments) < 3:
                continue
            knee, ankle = self.joint(*c.segments[:2]), self.joint(*c.segments[1:3])
            total += np.cross(knee - c.start, ankle - knee) / 0.4**2  # the knee flexes backward
            foot = self.centroid(c.segments[2]) - ankle
            total += np.cross(knee - ankle, foot) / (0.4 * max(float(np.median(np.linalg.norm(foot, axis=-1))), 1e-3))
            found = True
        if found:
            return total
        for i in arms:
            s = self.chains[i].segments
            first = 1 if len(s) == 4 else 0  # a shoulder segment first
            if len(s) < first + 2:
                continue
            shoulder = self.joint(s[first], s[first - 1]) if first else self.chains[i].start
            elbow = self.joint(s[first], s[first + 1])
            wrist = self.joint(s[first + 1], s[first + 2]) if len(s) > first + 2 else self.centroid(s[first + 1])
            total -= np.cross(elbow - shoulder, wrist - elbow) / 0.3**2  # the elbow flexes forward
            found = True
        return total if found else None

    def sides(self, pair, left) -> tuple[tuple, float]:
        """``pair`` ordered left first, and the weighted share of frames that agree (0.5 without a left)."""
        if len(pair) == 2 and abs(self.named[pair[0]][1] - self.named[pair[1]][1]) > 1.0:  # the names say
            first_left = self.named[pair[0]][1] > self.named[pair[1]][1]
            return (tuple(pair) if first_left else tuple(pair[::-1])), 1.0
        if len(pair) != 2 or left is None:
            return tuple(pair), 0.5
        along = np.einsum("fi,fi->f", self.chains[pair[0]].start - self.chains[pair[1]].start, left)
        along = along[np.isfinite(along)]
        total = np.abs(along).sum()
        if not total:
            return tuple(pair), 0.5
        share = float(np.abs(along[along > 0]).sum() / total)
        return (tuple(pair) if share >= 0.5 else tuple(pair[::-1])), max(share, 1.0 - share)

    def labelled(self, legs, arms, head) -> tuple[list[str], dict, dict]:
        """Labels per segment, ``{limb: segments}`` and the side shares of the leg and arm pairs."""
        labels = ["extra"] * self.size
        limbs, shares = {}, {}
        left = self.left(legs, arms)
        for group, names in ((legs, ("left_leg", "right_leg")), (arms, ("left_arm", "right_arm"))):
            order, shares[names[0].split("_")[1]] = self.sides(group, left)
            for limb, i in zip(names, order):
                limbs[limb] = self.chains[i].segments
        if head:
            limbs["head"] = self.chains[head[0]].segments
        for limb, segments in limbs.items():
            side = "" if limb == "head" else limb.split("_")[0] + "_"
            chain = next(i for i in (*legs, *arms, *head) if self.chains[i].segments == segments)
            for j, name in zip(segments, self.naming(limb.split("_")[-1], chain)[1]):
                labels[j] = name if name == "extra" else side + name.rstrip("+")
        pelvis = self.chains[legs[0]].attachment if legs else None
        thorax = self.chains[arms[0]].attachment if arms else None
        if pelvis is not None and pelvis == thorax:
            labels[pelvis] = "trunk"
        else:
            for j, name in ((pelvis, "pelvis"), (thorax, "thorax")):
                if j is not None:
                    labels[j] = name
            if pelvis is not None and thorax is not None:
                for j in self.core:
                    if labels[j] == "extra" and self.hop(pelvis, j) + self.hop(j, thorax) == self.hop(pelvis, thorax):
                        labels[j] = "spine"
                for i in arms[1:]:  # an arm on a segment next to the thorax (the shoulders split from it)
                    if labels[self.chains[i].attachment] == "extra":
                        labels[self.chains[i].attachment] = "thorax"
        if not head and legs and arms:  # a head the tree put among the core's segments: above the shoulders
            for j in self.core:
                if labels[j] in ("spine", "extra") and self.level(j, legs, arms) > _ABOVE_SHOULDERS:
                    labels[j] = "head"
                    break
        return labels, limbs, shares

    def off_midline(self, j: int, legs, arms) -> float:
        """How far segment ``j``'s markers are from the body's midline (the line from the hips' midpoint to the
        shoulders'), over half the shoulders' width (median over frames): 0 on the midline, 1 at a shoulder."""
        if len(arms) < 2:
            return 0.0
        shoulders = [self.chains[i].start for i in arms]
        mid = self.midpoint(arms)
        axis = mid - self.midpoint(legs)
        axis = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
        offset = self.centroid(j) - mid
        offset = offset - np.einsum("fi,fi->f", offset, axis)[:, None] * axis
        # over half the shoulders' width, at least 0.12 of the body's size (an arm may start at a shoulder segment
        # near the spine, which would put the two "shoulders" close together)
        half = np.maximum(0.5 * np.linalg.norm(shoulders[0] - shoulders[1], axis=-1), 0.12 * self.height)
        ratio = np.linalg.norm(offset, axis=-1) / half
        ratio = ratio[np.isfinite(ratio)]
        return float(np.median(ratio)) if len(ratio) else 0.0

    def level(self, j: int, legs, arms) -> float:
        """Where segment ``j``'s markers are along the body (median over frames): 0 at the hips, 1 at the
        shoulders (the legs' and arms' attachment joints)."""
        hips = self.midpoint(legs)
        span = self.midpoint(arms) - hips
        along = np.einsum("fi,fi->f", self.centroid(j) - hips, span) / np.maximum(np.einsum("fi,fi->f", span, span), 1e-12)
        along = along[np.isfinite(along)]
        return float(np.median(along)) if len(along) else 0.0


#: Assignments whose labels are compared with the best's for the confidences.
_COMPARED = 200


def label_anatomy(parents, joints: np.ndarray, markers: np.ndarray, marker_segment: np.ndarray,
                  names=None, max_frames: int = 500, hints=None) -> Anatomy:
    """Label a recovered tree against the human template (module docstring).

    Args:
        parents: ``(S,)`` parent segment of each segment (-1 for the root).
        joints: ``(F, S, 3)`` each segment's joint to its parent (the root's origin for the root), m.
        markers: ``(F, M, 3)`` marker positions (the fitted ones, gaps filled), m.
        marker_segment: ``(M,)`` the segment each marker is on.
        names: segment names for the messages (default ``segment <index>``).
        max_frames: frames (evenly spaced) looked at.
        hints: ``(M,)`` what each marker's name says (:func:`~bcmocap.markers.label_hints.marker_hints`), or None:
            a chain whose named markers are on another limb costs more (a soft prior), as does a chain the names put
            on a limb left unassigned; a chain with no limb marker's name (unnamed, or pelvis and shoulder names
            only) costs half as much on any limb; and names that tell a pair of limbs' sides apart decide them.

    Raises:
        ValueError: shapes that do not match (naming them).
    """
    parents = [int(p) for p in parents]
    joints, markers = np.asarray(joints, np.float64), np.asarray(markers, np.float64)
    marker_segment = np.asarray(marker_segment)
    size = len(parents)
    names = list(names) if names is not None else [f"segment {j}" for j in range(size)]
    if joints.ndim != 3 or joints.shape[1:] != (size, 3):
        raise ValueError(f"label_anatomy: joints must have shape (frames, {size}, 3), got {joints.shape}")
    if markers.ndim != 3 or markers.shape[0] != joints.shape[0] or markers.shape[2] != 3 \
            or marker_segment.shape != (markers.shape[1],):
        raise ValueError(f"label_anatomy: markers {markers.shape} and marker_segment {marker_segment.shape} do not "
                         f"match joints {joints.shape}")
    frames = np.unique(np.linspace(0, len(joints) - 1, min(max_frames, len(joints))).round().astype(int))
    if hints is not None and len(hints) != markers.shape[1]:
        raise ValueError(f"label_anatomy: {len(hints)} hints for {markers.shape[1]} markers")
    tree = _Tree(parents, joints[frames], markers[frames], marker_segment, hints)
    ranked = tree.assignments()
    best_cost, legs, arms, head = ranked[0]
    labels, limbs, shares = tree.labelled(legs, arms, head)
    # Confidence: how much cheaper the best assignment is than the best that labels the segment otherwise.
    margin = np.full(size, np.inf)
    for cost, *other in ranked[1:_COMPARED]:
        other_labels = tree.labelled(*other)[0]
        for j in range(size):
            if other_labels[j] != labels[j] and not np.isfinite(margin[j]):
                margin[j] = cost - best_cost
    confidence = 1.0 - np.exp(-margin)
    for limb, segments in limbs.items():  # a side decided by few frames is not sure either
        if limb != "head":
            confidence[list(segments)] = np.minimum(confidence[list(segments)], 2.0 * shares[limb.split("_")[1]] - 1.0)
    wrong, causes, notes = _verdict(tree, legs, arms, head, limbs, labels, names)
    return Anatomy(labels=tuple(labels), confidence=confidence, limbs=limbs, human=not wrong, wrong_limbs=wrong,
                   notes=tuple(notes), cost=best_cost, causes=causes)


def _verdict(tree: _Tree, legs, arms, head, limbs, labels, names) -> tuple[dict, dict, list[str]]:
    """``{limb: reason}`` for the arms, legs and head that are missing or implausible, ``{limb: (kind, segments)}``
    (:data:`CAUSES`) and the notes."""
    chains = tree.chains
    wrong, causes, notes = {}, {}, []

    def flag(limb: str, kind: str, segments, reason: str, replace: bool = True) -> None:
        if replace or limb not in wrong:
            wrong[limb], causes[limb] = reason, (kind, tuple(int(j) for j in segments))
    chain_of = {tree.chains[i].segments: i for i in (*legs, *arms, *head)}
    for limb in ("left_leg", "right_leg", "left_arm", "right_arm"):
        if limb not in limbs:
            left = [c for k, c in enumerate(chains) if k not in (*legs, *arms, *head)]
            flag(limb, "missing", [j for c in left for j in c.segments], "not found" + (
                ": no chain of segments fits it; " + "; ".join(
                    f"{' > '.join(names[j] for j in c.segments)} ({100 * c.reach:.0f} cm, from {names[c.attachment]})"
                    for c in left) + " hang(s) unplaced" if left else ": no chain of segments is left for it"))
            continue
        i = chain_of[limbs[limb]]
        _, naming = tree.naming(limb.split("_")[1], i)
        if naming == ("leg+",):
            flag(limb, "rigid_leg", limbs[limb], f"one rigid segment ({names[limbs[limb][0]]}) from hip to foot: its "
                 "markers were grouped across the knee")
            continue
        if naming[0] in ("arm+", "arm"):
            notes.append(f"the {limb.replace('_', ' ')} is one rigid segment ({names[limbs[limb][0]]}"
                         f"{' with its hand apart' if naming[0] == 'arm' else ''}): its elbow did not move")
        for j, name, length in zip(limbs[limb], naming, chains[i].lengths):
            if (tree.marker_segment == j).sum() < 2:
                continue  # one marker has no rigid frame: its segment's joint, and length, are not determined
            if name == "extra":
                flag(limb, "too_many", limbs[limb],
                     f"{len(naming)} segments, more than a {limb.split('_')[1]} has ({names[j]} and after)")
                break
            ratio = length / tree.height / _LENGTHS[name]
            if not 0.5 <= ratio <= 2.0:
                flag(limb, "length", [j], f"{names[j]}, its {name.rstrip('+').replace('_', ' ')}, is "
                     f"{100 * length:.0f} cm long where one is about {100 * _LENGTHS[name] * tree.height:.0f} cm: it "
                     "holds another limb's markers, or a segment hangs from the wrong one")
                break
    if len(legs) == 2 and tree.hop(chains[legs[0]].attachment, chains[legs[1]].attachment) > 1:
        for limb in ("left_leg", "right_leg"):
            flag(limb, "legs_apart", limbs[limb], "the legs hang from segments apart in the tree, not from one pelvis",
                 replace=False)
    axis = tree.body_axis(legs, arms)
    if axis is not None:
        for limb in ("left_leg", "right_leg"):
            if limb in limbs and tree.hanging(chain_of[limbs[limb]], axis) > 0.0:
                flag(limb, "not_hanging", limbs[limb], "its end does not hang away from the thorax: the chain is "
                     "probably not a leg", replace=False)
    if legs and axis is not None:
        pelvis = chains[legs[0]].attachment
        if tree.extent(pelvis, axis) < _TRUNK_EXTENT:  # a pelvis alone: nothing above the legs hangs from it
            for limb in ("left_arm", "right_arm", "head"):
                if limb in limbs and chains[chain_of[limbs[limb]]].attachment == pelvis:
                    flag(limb, "on_pelvis", [pelvis], f"hangs from the pelvis ({names[pelvis]}), not from the "
                         "thorax: the trunk barely moved relative to the pelvis")
                    labels[pelvis] = "pelvis"
    for j in tree.core:
        if labels[j] == "head" and len(tree.nbrs[j]) >= 2:
            flag("head", "head_in_trunk", [j, *sorted(tree.nbrs[j])], f"{names[j]} is among the trunk's segments, "
                 f"joined to {' and '.join(names[k] for k in sorted(tree.nbrs[j]))}; a head hangs from the thorax only")
    if "trunk" in labels:
        notes.append("the pelvis and the thorax are one segment (they did not move relative to each other)")
    if not head:
        notes.append("no head segment: the head carries no markers or moved with the thorax")
    extra = [names[j] for j, label in enumerate(labels) if label == "extra"]
    if extra:
        notes.append(f"segments with no place in the template: {', '.join(extra)}")
    return wrong, causes, notes


#: Which labels the human template joins (either side of a limb; a limb's segments only on its own side).
_JOINED = {frozenset(pair) for pair in (
    ("pelvis", "spine"), ("pelvis", "thorax"), ("spine", "spine"), ("spine", "thorax"), ("pelvis", "thigh"),
    ("trunk", "thigh"), ("thigh", "shin"), ("shin", "foot"), ("foot", "toes"), ("shin", "ankle"), ("ankle", "foot"),
    ("thorax", "shoulder"), ("thorax", "upper_arm"), ("trunk", "shoulder"), ("trunk", "upper_arm"),
    ("shoulder", "upper_arm"), ("upper_arm", "forearm"), ("forearm", "hand"),
    ("thorax", "neck"), ("thorax", "head"), ("trunk", "neck"), ("trunk", "head"), ("neck", "head"),
    ("spine", "shoulder"), ("spine", "upper_arm"),
    ("thorax", "arm"), ("trunk", "arm"), ("spine", "arm"), ("shoulder", "arm"), ("arm", "hand"))}


def template_penalties(segment_groups, anatomy: Anatomy, num_groups: int, factor: float,
                       min_confidence: float = 0.5) -> np.ndarray:
    """``(G, G)`` multipliers of the groups' joint costs: ``factor`` where the two groups' labels (segment ``k`` is
    group ``segment_groups[k]``), each at least ``min_confidence`` sure, are not joined in the human template (or
    are a limb's segments on different sides), 1 elsewhere and wherever a label is ``"extra"``."""
    label = {int(g): (anatomy.labels[k], float(anatomy.confidence[k])) for k, g in enumerate(segment_groups)}
    out = np.ones((num_groups, num_groups))
    if factor <= 0:
        return out
    for a in range(num_groups):
        for b in range(a + 1, num_groups):
            (la, ca), (lb, cb) = label.get(a, ("extra", 0.0)), label.get(b, ("extra", 0.0))
            if "extra" in (la, lb) or min(ca, cb) < min_confidence:
                continue
            side_a, side_b = (la.split("_")[0] if la.startswith(("left_", "right_")) else None,
                              lb.split("_")[0] if lb.startswith(("left_", "right_")) else None)
            base_a, base_b = (la.split("_", 1)[1] if side_a else la), (lb.split("_", 1)[1] if side_b else lb)
            joined = frozenset((base_a, base_b)) in _JOINED and not (side_a and side_b and side_a != side_b)
            if not joined:
                out[a, b] = out[b, a] = factor
    return out


#: Pairs of body regions no joint joins (:func:`region_penalties`).
_APART = {frozenset(pair) for pair in (("leg", "arm"), ("leg", "head"), ("leg", "trunk"), ("head", "pelvis"))}


def body_regions(markers: np.ndarray, marker_group: np.ndarray, num_groups: int) -> list[str]:
    """Each group's body region from where its markers are, without the tree: ``"leg"``, ``"pelvis"``,
    ``"trunk"``, ``"arm"``, ``"head"`` or ``"?"``; all ``"?"`` when no axis stands out (a body as wide as it is
    tall in most frames: rolling, crouching). Used where the labels of a wrong tree cannot be trusted.

    Up is the lab axis along which the markers spread farthest (5th to 95th percentile, median over frames), its
    sign the side where the markers move slowest (feet in stance); a group's height is its markers' median
    height between the frame's 5th and 95th percentiles (0 the floor, 1 the head), its lateral offset their
    median horizontal distance from the frame's median marker over the body's height. Below 0.47 is a leg; above
    0.92 near the midline a head; beside the body (offset 0.17 or more) an arm; near the midline a pelvis below
    0.72 and a trunk above. On real walks: thighs 0.32-0.43, arms 0.51-0.85 and 0.17-0.23 aside, pelvis 0.56-0.65.
    """
    regions = ["?"] * num_groups
    m = np.asarray(markers, np.float64)
    lo, hi = np.nanpercentile(m, 5, axis=1), np.nanpercentile(m, 95, axis=1)  # (F, 3)
    extent = np.nanmedian(hi - lo, axis=0)
    up = int(np.argmax(extent))
    horizontal = [a for a in range(3) if a != up]
    if extent[up] < 1.4 * max(extent[a] for a in horizontal):
        return regions  # lying, rolling, crouching: heights say nothing
    h = m[..., up]
    speed = np.linalg.norm(np.diff(m, axis=0), axis=-1)
    frac = (h - lo[:, up, None]) / np.maximum(hi[:, up, None] - lo[:, up, None], 1e-9)
    low, high = frac[:-1] < 0.1, frac[:-1] > 0.9
    if low.any() and high.any() and np.nanmedian(speed[low]) > np.nanmedian(speed[high]):
        frac = 1.0 - frac  # the slow end is the floor
    size = float(np.nanmedian(hi[:, up] - lo[:, up]))
    centre = np.nanmedian(m[..., horizontal], axis=1, keepdims=True)
    lateral = np.linalg.norm(m[..., horizontal] - centre, axis=-1) / max(size, 1e-9)
    for g in range(num_groups):
        own = marker_group == g
        if not own.any():
            continue
        height, aside = float(np.nanmedian(frac[:, own])), float(np.nanmedian(lateral[:, own]))
        if height < 0.47:
            regions[g] = "leg"
        elif height > 0.92 and aside < 0.12:
            regions[g] = "head"
        elif aside >= 0.17 and height < 0.92:
            regions[g] = "arm"
        elif aside < 0.17:
            regions[g] = "pelvis" if height < 0.72 else "trunk"
    return regions


def region_penalties(regions, factor: float) -> np.ndarray:
    """``(G, G)`` multipliers of the joint costs: ``factor`` between regions no joint joins (a leg and an arm, the
    trunk or the head; the head and the pelvis; an arm and the pelvis where a trunk is found), 1 elsewhere."""
    num = len(regions)
    apart = _APART | ({frozenset(("arm", "pelvis"))} if "trunk" in regions else set())
    out = np.ones((num, num))
    for a in range(num):
        for b in range(a + 1, num):
            if frozenset((regions[a], regions[b])) in apart:
                out[a, b] = out[b, a] = factor
    return out
