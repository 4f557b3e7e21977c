"""What marker names say (bcmocap.markers.label_hints): sides and regions of the common marker sets, and the soft
prior they give the segmentation and the tree."""

import numpy as np

from bcmocap.markers import MarkerTrajectories, segment_markers
from bcmocap.markers.label_hints import (
    MarkerHint,
    group_label_penalties,
    informative,
    marker_hints,
    marker_label_weights,
)


def test_names_of_the_common_marker_sets_give_sides_and_regions():
    plug_in_gait = ["Male:LTHI", "Male:RKNE", "LASI", "C7", "RBAK", "LWRA", "RFIN", "LFHD", "LSHO", "RTIB"]
    assert [(h.side, h.region) for h in marker_hints(plug_in_gait)] == [
        ("L", "thigh"), ("R", "knee"), ("L", "pelvis"), (None, "trunk"), (None, "trunk"), ("L", "wrist"),
        ("R", "hand"), (None, "head"), ("L", "shoulder"), ("R", "shank")]
    helen_hayes = ["RSHA", "L.TO", "THEA", "RHEA", "LKNE#2", "ROFF"]
    assert [(h.side, h.region) for h in marker_hints(helen_hayes)] == [
        ("R", "shank"), ("L", "foot"), (None, "head"), (None, "head"), ("L", "knee"), (None, "trunk")]
    anatomical = ["L_FTC", "R_FLE", "L_FAL", "CV7", "L_HLE", "R_SAJ", "L_WAND1", "*12"]
    hints = marker_hints(anatomical)
    assert [(h.side, h.region) for h in hints[:6]] == [
        ("L", "thigh"), ("R", "knee"), ("L", "ankle"), (None, "trunk"), ("L", "elbow"), ("R", "shoulder")]
    assert hints[6:] == [None, None]  # a wand, an unlabelled trajectory: nothing said


def test_a_subject_initial_before_every_name_is_dropped():
    # MocapRecovery's rolling trial: every name starts with the subject's L, then the side.
    names = ["LRFHD", "LL_FTC", "LR_FTC", "LL_SK1", "LR-SK2", "LCLAV", "LLUA1", "LR_HLE"]
    assert [(h.side, h.region) for h in marker_hints(names)] == [
        (None, "head"), ("L", "thigh"), ("R", "thigh"), ("L", "shank"), ("R", "shank"), (None, "trunk"),
        ("L", "upper_arm"), ("R", "elbow")]
    # an unlabelled trajectory among them changes nothing; a label with a copy suffix and spaces is read
    assert [h and (h.side, h.region) for h in marker_hints([*names, "*12", " LRKNE#2 "])][-3:] == [
        ("R", "elbow"), None, ("R", "knee")]


def test_a_limb_marker_without_a_side_and_too_few_names_say_nothing():
    assert marker_hints(["THI", "KNE"]) == [None, None]
    assert not informative(marker_hints(["LTHI", "RTHI", "LKNE"]))  # too few
    assert not informative(marker_hints([f"LTH{k}" for k in range(12)]))  # one side only
    assert informative(marker_hints([f"{s}{c}" for s in "LR" for c in ("THI", "KNE", "TIB", "ANK", "HEE")]))


def test_markers_on_bones_no_segment_holds_together_are_weighed_down():
    hints = marker_hints(["LTHI", "LKNE", "LTIB", "RTHI", "LASI", "RASI", "C7", "LFHD", "*3"])
    w = marker_label_weights(hints, 100.0)
    i = {n: k for k, n in enumerate(["LTHI", "LKNE", "LTIB", "RTHI", "LASI", "RASI", "C7", "LFHD", "*3"])}
    together = [("LTHI", "LKNE"), ("LKNE", "LTIB"), ("LASI", "RASI"), ("LTHI", "*3")]  # a knee marker: either bone
    apart = [("LTHI", "LTIB"), ("LTHI", "RTHI"), ("LTHI", "LASI"), ("C7", "LFHD"), ("C7", "LASI")]
    assert all(w[i[a], i[b]] == 1.0 for a, b in together)
    assert all(w[i[a], i[b]] == w[i[b], i[a]] == 0.01 for a, b in apart)
    assert (marker_label_weights(hints, 0.0) == 1.0).all()


def test_segments_no_joint_of_the_body_joins_are_penalised():
    labels = ["LASI", "RASI", "LTHI", "LKNE", "LTIB", "LANK", "LHEE", "LTOE", "RTHI", "RTIB", "*9"]
    groups = np.array([0, 0, 1, 1, 2, 2, 3, 3, 4, 5, 6])
    p = group_label_penalties(marker_hints(labels), groups, 7, 10.0)
    joined = [(0, 1), (1, 2), (2, 3), (0, 4), (4, 5)]
    apart = [(0, 3), (0, 2), (1, 5), (2, 5), (1, 4)]  # a foot or a shank on the pelvis, a left on a right…
    assert all(p[a, b] == 1.0 for a, b in joined)
    assert all(p[a, b] == p[b, a] == 10.0 for a, b in apart)
    assert (p[6] == 1.0).all()  # an unnamed segment: no prior
    # A segment of a knee and a shin marker is a shin (the bone both may lie on): not on the pelvis.
    p = group_label_penalties(marker_hints(["LASI", "RASI", "RKNE", "RSHA", "RTHI"]), np.array([0, 0, 1, 1, 2]), 3, 10.0)
    assert p[0, 1] == 10.0 and p[0, 2] == 1.0 and p[1, 2] == 1.0


def test_names_split_two_segments_the_motion_cannot_tell_apart():
    """A thigh and a shin that never bend: every marker is rigid with every other, so the motion alone splits
    them at random; their names split them as named, and a marker the names leave open goes where it is rigid."""
    rng = np.random.default_rng(0)
    frames = 300
    body = rng.normal(size=(7, 3)) * 0.1
    angles = np.cumsum(rng.normal(size=(frames, 3)) * 0.05, axis=0)
    from scipy.spatial.transform import Rotation

    rotations = Rotation.from_rotvec(angles).as_matrix()
    positions = np.einsum("fij,mj->fmi", rotations, body) + np.cumsum(rng.normal(size=(frames, 1, 3)) * 0.01, 0)
    positions += rng.normal(size=positions.shape) * 1e-4
    labels = ["LTH1", "LTH2", "LTH3", "LSH1", "LSH2", "LSH3", "LKNE"]
    trajectories = MarkerTrajectories.from_array(positions, 100.0, labels)
    hints = marker_hints(labels)
    seg = segment_markers(trajectories, 2, label_weights=marker_label_weights(hints, 100.0))
    assert len({int(seg.groups[k]) for k in range(3)}) == 1 and len({int(seg.groups[k]) for k in range(3, 6)}) == 1
    assert seg.groups[0] != seg.groups[3]
    assert hints[6] == MarkerHint("L", "knee") and hints[6].bones() == ("thigh", "shank")


def test_a_group_holding_two_named_bones_is_split_with_its_joint_marker_where_it_is_most_rigid():
    from bcmocap.markers.segmentation import split_named_conflicts

    labels = ["RUPA", "RELB", "RFRM", "RWRA", "C7"]
    weights = marker_label_weights(marker_hints(labels), 100.0)
    reference = np.full((5, 5), 0.002)
    reference[1, 2] = reference[2, 1] = 0.0005  # the elbow marker moves with the forearm's
    groups = np.array([0, 0, 0, 0, 1])
    split = split_named_conflicts(groups, weights, reference)
    assert split[1] == split[2] == split[3] != split[0]  # the upper arm apart; elbow, forearm and wrist together
    untouched = np.array([0, 0, 1, 1, 2])
    assert (split_named_conflicts(untouched, weights, reference) == untouched).all()


def test_a_named_marker_alone_joins_the_segment_of_its_bone_where_it_is_rigid_with_it():
    from bcmocap.markers.segmentation import merge_named_singles

    labels = ["RTHI", "RKNE", "RTIB", "RANK", "LTHI", "*5"]
    weights = marker_label_weights(marker_hints(labels), 100.0)
    reference = np.full((6, 6), 0.05)
    reference[0, 1] = reference[1, 0] = 0.02  # RTHI moves with RKNE within 30 mm
    reference[0, 2] = reference[2, 0] = 0.001  # and more rigidly with the shin's RTIB, a bone it is not on
    np.fill_diagonal(reference, 0.0)
    groups = np.array([0, 1, 2, 2, 3, 4])  # RTHI, RKNE, LTHI and the unnamed *5 alone
    merged = merge_named_singles(groups, weights, reference, 0.03)
    assert merged.tolist() == [0, 0, 1, 1, 2, 3]  # RTHI with RKNE; LTHI (nothing rigid) and *5 (unnamed) stay
    assert merge_named_singles(groups, weights, reference, 0.01).tolist() == [0, 1, 2, 2, 3, 4]


def test_with_the_eigengap_the_names_split_what_the_motion_cannot_and_the_count_follows():
    """Thigh and shin markers that never move apart, segmented with the eigengap: the names split them, and the
    segmentation's count agrees with its groups."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    frames = 300
    body = rng.normal(size=(6, 3)) * 0.1
    rotations = Rotation.from_rotvec(np.cumsum(rng.normal(size=(frames, 3)) * 0.05, axis=0)).as_matrix()
    positions = np.einsum("fij,mj->fmi", rotations, body) + rng.normal(size=(frames, 6, 3)) * 1e-4
    labels = ["LTH1", "LTH2", "LTH3", "LSH1", "LSH2", "LSH3"]
    trajectories = MarkerTrajectories.from_array(positions, 100.0, labels)
    seg = segment_markers(trajectories, None, rigid_tolerance_m=0.015,
                          label_weights=marker_label_weights(marker_hints(labels), 100.0))
    assert seg.num_groups == seg.groups.max() + 1 == 2
    assert len(set(seg.groups[:3])) == len(set(seg.groups[3:])) == 1 and seg.groups[0] != seg.groups[3]


def test_a_label_prior_between_0_and_1_is_refused():
    import pytest

    from bcmocap.markers import MarkerOptions, fit_marker_skeleton
    from bcmocap.precision import enable_float64

    enable_float64()
    trajectories = MarkerTrajectories.from_array(np.zeros((10, 3, 3)), 100.0, ["a", "b", "c"])
    with pytest.raises(ValueError, match="label_prior must be 0 .off. or at least 1, got 0.5"):
        fit_marker_skeleton(trajectories, MarkerOptions(label_prior=0.5))
