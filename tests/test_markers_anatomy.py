"""The human template of recovered marker trees (bcmocap.markers.anatomy): labels, sides and the verdict."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bcmocap.kinematics.fk import joint_positions
from bcmocap.markers.anatomy import label_anatomy
from bcmocap.sim.markers import full_body_markers, marker_positions
from bcmocap.sim.motions import load_body_motion


@pytest.fixture(scope="module")
def walk():
    """The CMU walk's skeleton (pelvis, torso, head and the limbs' three segments each), its joints and a 45-marker
    set, 4 s at 30 fps."""
    skeleton, motion = load_body_motion("walk", fps=30, seconds=4.0)
    specs = full_body_markers(skeleton, jitter_m=0.01, seed=0)
    joints = np.asarray(joint_positions(skeleton, motion))
    markers = marker_positions(skeleton, motion, specs)
    segment = np.array([skeleton.index(s.segment) for s in specs])
    return skeleton, joints, markers, segment


def _expected(name: str) -> str:
    return {"torso": "thorax"}.get(name, name)


def _rerooted(parents, root):
    """The same tree hung from ``root``: each segment's new parent and the segment whose origin is its new joint."""
    neighbours = {j: set() for j in range(len(parents))}
    for j, p in enumerate(parents):
        if p >= 0:
            neighbours[j].add(p)
            neighbours[p].add(j)
    new, origin, frontier = {root: -1}, {root: root}, [root]
    while frontier:
        j = frontier.pop()
        for k in neighbours[j] - set(new):
            new[k], origin[k] = j, (k if parents[k] == j else j)
            frontier.append(k)
    return [new[j] for j in range(len(parents))], [origin[j] for j in range(len(parents))]


@pytest.mark.parametrize("turn", ["upright", "lying", "any", "rerooted"])
def test_the_true_tree_of_a_walk_is_a_human_in_any_orientation_and_from_any_root(walk, turn):
    skeleton, joints, markers, segment = walk
    parents = list(skeleton.parents)
    if turn == "rerooted":  # the tree as the pipeline might hang it: from the head
        parents, origin = _rerooted(parents, skeleton.index("head"))
        joints = joints[:, origin]
    elif turn != "upright":
        r = (Rotation.from_euler("x", 90, degrees=True) if turn == "lying" else Rotation.random(random_state=3)).as_matrix()
        joints, markers = joints @ r.T, markers @ r.T
    anatomy = label_anatomy(parents, joints, markers, segment, names=skeleton.names)
    assert anatomy.human and anatomy.wrong_limbs == {}
    assert list(anatomy.labels) == [_expected(n) for n in skeleton.names]
    assert (anatomy.confidence > 0.5).all()
    assert anatomy.limbs["left_leg"] == tuple(skeleton.index(f"left_{s}") for s in ("thigh", "shin", "foot"))


def test_a_leg_hung_on_an_arm_is_named(walk):
    skeleton, joints, markers, segment = walk
    parents = list(skeleton.parents)
    parents[skeleton.index("left_thigh")] = skeleton.index("right_hand")  # the hip placed where it is, the parent wrong
    anatomy = label_anatomy(parents, joints, markers, segment, names=skeleton.names)
    assert not anatomy.human
    assert set(anatomy.wrong_limbs) & {"left_leg", "right_arm"}
    assert "right_hand" in " ".join(anatomy.wrong_limbs.values()) or "left_leg" in anatomy.wrong_limbs


def test_arms_hung_on_the_pelvis_are_wrong_unless_one_segment_holds_the_whole_trunk(walk):
    skeleton, joints, markers, segment = walk
    parents = list(skeleton.parents)
    pelvis, torso = skeleton.index("pelvis"), skeleton.index("torso")
    for side in ("left", "right"):  # the arms' joints where they are, on the pelvis (the trunk did not move on it)
        parents[skeleton.index(f"{side}_upper_arm")] = pelvis
    parents[skeleton.index("head")] = pelvis
    anatomy = label_anatomy(parents, joints, markers, segment, names=skeleton.names)
    assert not anatomy.human and {"left_arm", "right_arm"} <= set(anatomy.wrong_limbs)
    assert "hangs from the pelvis (pelvis)" in anatomy.wrong_limbs["left_arm"]
    # The torso's markers given to the pelvis: one segment holds the whole trunk, and it is a body.
    merged = np.where(segment == torso, pelvis, segment)
    keep = [j for j in range(skeleton.num_segments) if j != torso]
    index = {j: k for k, j in enumerate(keep)}
    parents2 = [index[parents[j]] if parents[j] >= 0 else -1 for j in keep]
    anatomy = label_anatomy(parents2, joints[:, keep], markers, np.array([index[j] for j in merged]),
                            names=[skeleton.names[j] for j in keep])
    assert anatomy.human and anatomy.labels[index[pelvis]] == "trunk"
    assert any("one segment" in note for note in anatomy.notes)


def test_a_leg_grouped_across_the_knee_is_wrong(walk):
    skeleton, joints, markers, segment = walk
    thigh, shin, foot = (skeleton.index(f"left_{s}") for s in ("thigh", "shin", "foot"))
    merged = np.where(np.isin(segment, [shin, foot]), thigh, segment)
    keep = [j for j in range(skeleton.num_segments) if j not in (shin, foot)]
    index = {j: k for k, j in enumerate(keep)}
    parents = [index[skeleton.parents[j]] if skeleton.parents[j] >= 0 else -1 for j in keep]
    anatomy = label_anatomy(parents, joints[:, keep], markers, np.array([index[j] for j in merged]),
                            names=[skeleton.names[j] for j in keep])
    assert not anatomy.human and list(anatomy.wrong_limbs) == ["left_leg"]
    assert "across the knee" in anatomy.wrong_limbs["left_leg"]


def test_shapes_that_do_not_match_are_named(walk):
    skeleton, joints, markers, segment = walk
    with pytest.raises(ValueError, match=r"joints must have shape \(frames, 15, 3\)"):
        label_anatomy(skeleton.parents, joints[:, :3], markers, segment)
    with pytest.raises(ValueError, match="marker_segment"):
        label_anatomy(skeleton.parents, joints, markers, segment[:-1])


def test_the_template_prior_moves_arms_from_the_pelvis_to_the_thorax_where_the_data_barely_prefer_the_pelvis(walk):
    from bcmocap.markers.anatomy import template_penalties
    from bcmocap.markers.joints import minimum_spanning_tree

    skeleton, joints, markers, segment = walk
    parents = list(skeleton.parents)
    pelvis, torso = skeleton.index("pelvis"), skeleton.index("torso")
    arms = [skeleton.index(f"{side}_upper_arm") for side in ("left", "right")]
    for arm in arms:
        parents[arm] = pelvis
    anatomy = label_anatomy(parents, joints, markers, segment, names=skeleton.names)
    assert not anatomy.human
    # Joint costs that fit that tree (the trunk barely moved on the pelvis: an arm's joint with either is as good).
    q = np.full((15, 15), 1e-3)
    for j, p in enumerate(parents):
        if p >= 0:
            q[j, p] = q[p, j] = 1e-5
    for arm in arms:
        q[arm, torso] = q[torso, arm] = 2e-5
    groups = np.arange(15)  # segment k is group k
    penalty = template_penalties(groups, anatomy, 15, 10.0)
    assert penalty[arms[0], pelvis] == 10.0 and penalty[arms[0], torso] == 1.0
    assert penalty[skeleton.index("left_thigh"), pelvis] == 1.0  # what the template joins is left alone
    assert penalty[skeleton.index("left_shin"), skeleton.index("right_thigh")] == 10.0  # sides do not mix
    edges = {frozenset(e) for e in minimum_spanning_tree(q * penalty)}
    assert {frozenset((arm, torso)) for arm in arms} <= edges
    assert not any(frozenset((arm, pelvis)) in edges for arm in arms)
    assert (template_penalties(groups, anatomy, 15, 0.0) == 1.0).all()


def test_body_regions_come_from_where_the_markers_are_without_the_tree(walk):
    from bcmocap.markers.anatomy import body_regions, region_penalties

    skeleton, joints, markers, segment = walk
    regions = dict(zip(skeleton.names, body_regions(markers, segment, skeleton.num_segments)))
    assert regions["pelvis"] == "pelvis" and regions["torso"] == "trunk" and regions["head"] == "head"
    assert all(regions[f"{side}_{part}"] == "leg" for side in ("left", "right") for part in ("thigh", "shin", "foot"))
    # The studio's arms hang close to its narrow body: only the hands are far enough aside to be called arms
    # (real walks: 0.17-0.23 of the height aside); no part of an arm is taken for a leg.
    assert all(regions[f"{side}_hand"] == "arm" for side in ("left", "right"))
    assert not any(regions[f"{side}_{part}"] == "leg" for side in ("left", "right") for part in ("upper_arm", "forearm", "hand"))
    penalty = region_penalties(list(regions.values()), 10.0)
    index = skeleton.index
    assert penalty[index("left_thigh"), index("left_hand")] == 10.0  # a leg on an arm: no joint joins them
    assert penalty[index("left_thigh"), index("left_upper_arm")] == 10.0  # nor a leg on the trunk's region
    assert penalty[index("left_thigh"), index("pelvis")] == 1.0 and penalty[index("left_thigh"), index("left_shin")] == 1.0
    assert penalty[index("left_hand"), index("pelvis")] == 10.0  # an arm on the pelvis, where a trunk is found
    # A lab whose vertical is another axis (Y up, as some systems write): the same regions.
    y_up = markers @ np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]).T
    assert body_regions(y_up, segment, skeleton.num_segments) == list(regions.values())
    # A body as wide as it is tall in most frames (no axis stands out): no region, no penalty.
    blob = np.random.default_rng(0).normal(size=markers.shape)
    assert set(body_regions(blob, segment, skeleton.num_segments)) == {"?"}


def test_names_that_tell_the_sides_apart_decide_them_where_the_geometry_is_mirrored(walk):
    """A mirror image of the walk: the knees' and elbows' bending puts its left on the right; the markers' names
    (LTH1, RSH2, …) put it back, and a chain the names put on an arm costs more as a leg."""
    from bcmocap.markers.label_hints import marker_hints
    from bcmocap.sim.markers import full_body_markers

    skeleton, joints, markers, segment = walk
    specs = full_body_markers(skeleton, jitter_m=0.01, seed=0)
    hints = marker_hints([s.name for s in specs])
    mirror = np.array([-1.0, 1.0, 1.0])
    parents = list(skeleton.parents)
    left_leg = tuple(skeleton.index(f"left_{s}") for s in ("thigh", "shin", "foot"))
    mirrored = label_anatomy(parents, joints * mirror, markers * mirror, segment, names=skeleton.names)
    assert mirrored.limbs["right_leg"] == left_leg  # the geometry alone
    named = label_anatomy(parents, joints * mirror, markers * mirror, segment, names=skeleton.names, hints=hints)
    assert named.human and named.limbs["left_leg"] == left_leg
    assert list(named.labels) == [_expected(n) for n in skeleton.names]
    with pytest.raises(ValueError, match="3 hints for 45 markers"):
        label_anatomy(parents, joints, markers, segment, hints=hints[:3])
