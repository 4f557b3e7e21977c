"""Wearable sensors of the capture studio: IMU in each body camera and foot contacts (bcmocap.sim.sensors), their
files (bcmocap.io.sensors) and the gyro integration residual terms reuse."""

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from bcmocap.geometry import matrix_from_quat, quat_exp, quat_multiply
from bcmocap.io.sensors import (
    ContactRecording,
    integrate_gyro,
    read_contacts,
    read_imu,
    write_contacts,
    write_imu,
)
from bcmocap.kinematics.fk import forward_kinematics
from bcmocap.sim import standard_rig
from bcmocap.sim.studio import _body_motion
from bcmocap.sim.sensors import (
    ACCEL_BIAS,
    ACCEL_NOISE,
    GYRO_BIAS,
    GYRO_NOISE,
    default_imu_rate,
    simulate_contacts,
    simulate_imu,
    write_sensor_data,
)

FPS = 60.0
LEAD = 15  # frames between a clap and the trial, as the studio's 0.25 s at 60 fps
CONJ = np.array([1.0, -1.0, -1.0, -1.0])
EXACT = dict(gyro_noise=0.0, gyro_bias=0.0, accel_noise=0.0, accel_bias=0.0)


def _angle(q_a, q_b):
    """Geodesic angle (rad) between wxyz quaternions."""
    rel = quat_multiply(q_a * CONJ, q_b)
    return 2.0 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0]))


def _log(q):
    q = np.where(q[..., :1] < 0, -q, q)
    n = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    return 2.0 * np.arctan2(n, q[..., :1]) / np.maximum(n, 1e-300) * q[..., 1:]


@pytest.fixture(scope="module")
def walk():
    """2 s of the CMU walk through the standard rig, its claps, and the true IMU poses per trial frame."""
    skeleton, motion = _body_motion("walk", FPS, 2.0)  # load_body_motion, cached for the studio test below
    rig = standard_rig(skeleton, 64, 36)
    claps = np.array([-LEAD, motion.num_frames - 1 + LEAD])
    imu = simulate_imu(skeleton, rig, motion, FPS, claps, seed=4, **EXACT)
    cams = np.asarray(rig.world_from_camera(forward_kinematics(skeleton, motion)).wxyz_xyz)
    rot = quat_multiply(cams[..., :4], imu.camera_from_imu[:, :4])  # (T, C, 4) world_from_imu rotations
    pos = cams[..., 4:] + np.einsum("tcij,cj->tci", matrix_from_quat(cams[..., :4]), imu.camera_from_imu[:, 4:])
    return dict(skeleton=skeleton, rig=rig, motion=motion, claps=claps, imu=imu, rot=rot, pos=pos)


def _frame_time(frame, claps):
    return (np.asarray(frame, np.float64) - claps[0]) / FPS


def test_imu_layout(walk):
    imu, motion, rig = walk["imu"], walk["motion"], walk["rig"]
    assert imu.rate == default_imu_rate(FPS) == 240.0
    assert imu.cameras == rig.names
    n = int(round((motion.num_frames - 1 + 2 * LEAD) / FPS * imu.rate)) + 1  # first clap to second, inclusive
    assert imu.gyro.shape == imu.accel.shape == (n, rig.num_cameras, 3) and imu.time.shape == (n,)
    assert imu.time[0] == 0.0 and imu.time[-1] == pytest.approx(_frame_time(motion.num_frames - 1 + LEAD, walk["claps"]))
    mount_angle = np.degrees(2 * np.arccos(np.clip(imu.camera_from_imu[:, 0], -1, 1)))
    assert np.all(mount_angle <= 2.0) and np.all(np.abs(imu.camera_from_imu[:, 4:]) <= 0.005)
    assert np.ptp(mount_angle) > 0.1  # one rotation per camera, not one for all


@pytest.mark.parametrize("rate", [None, 200.0])
def test_noiseless_gyro_integrates_to_the_true_relative_rotation(walk, rate):
    imu = walk["imu"] if rate is None else simulate_imu(walk["skeleton"], walk["rig"], walk["motion"], FPS, walk["claps"],
                                                        rate=rate, seed=4, **EXACT)
    rot, last = walk["rot"], walk["motion"].num_frames - 1
    first = np.array([0, 0, 10, 47, 47, 100, last - 1, 0])
    second = np.array([1, 2, 11, 48, 49, 104, last, last])  # frame 47-48 of the walk: a 35° foot glitch
    rel = integrate_gyro(imu.time, imu.gyro, _frame_time(first, walk["claps"]), _frame_time(second, walk["claps"]))
    true = quat_multiply(rot[first] * CONJ, rot[second])
    assert rel.shape == (len(first), walk["rig"].num_cameras, 4)
    assert np.max(_angle(true, rel)) < 1e-4
    # from the first clap (the subject holds frame 0) to the second (holding the last frame)
    whole = integrate_gyro(imu.time, imu.gyro, 0.0, _frame_time(last + LEAD, walk["claps"]))
    assert np.max(_angle(quat_multiply(rot[0] * CONJ, rot[last]), whole)) < 1e-4
    # backwards gives the inverse
    back = integrate_gyro(imu.time, imu.gyro, _frame_time(11, walk["claps"]), _frame_time(10, walk["claps"]))
    assert np.max(_angle(true[2] * CONJ, back)) < 1e-4


def test_sensors_at_frame_times_match_finite_differences(walk):
    """At a frame, the gyro is the mean of the two one-frame rotations and the IMU's world acceleration the central
    second difference of its positions (the interpolant's documented end conditions)."""
    imu, rot, pos, claps = walk["imu"], walk["rot"], walk["pos"], walk["claps"]
    frames = np.array([5, 30, 47, 90])
    k = np.round(_frame_time(frames, claps) * imu.rate).astype(int)
    fd_gyro = 0.5 * (_log(quat_multiply(rot[frames - 1] * CONJ, rot[frames]))
                     + _log(quat_multiply(rot[frames] * CONJ, rot[frames + 1]))) * FPS
    np.testing.assert_allclose(imu.gyro[k], fd_gyro, atol=1e-9)
    accel = (pos[frames + 1] - 2 * pos[frames] + pos[frames - 1]) * FPS**2 + np.array([0.0, 0.0, 9.81])
    fd_accel = np.einsum("fcji,fcj->fci", matrix_from_quat(rot[frames]), accel)
    np.testing.assert_allclose(imu.accel[k], fd_accel, atol=1e-7)


def test_noiseless_imu_at_rest_reads_gravity_up(walk):
    imu, rot, claps = walk["imu"], walk["rot"], walk["claps"]
    rest = imu.time <= _frame_time(-1, claps) + 1e-12  # holding frame 0 since the first clap
    assert rest.sum() > 40
    up = np.einsum("cji,j->ci", matrix_from_quat(rot[0]), [0.0, 0.0, 9.81])  # world +Z in each IMU frame
    np.testing.assert_allclose(imu.accel[rest], np.broadcast_to(up, imu.accel[rest].shape), atol=1e-9)
    # the gyro's bump for the abrupt start at frame 0 leaks into the frame before it, 100 times less per frame
    assert np.max(np.abs(imu.gyro[rest])) < 0.02
    assert np.max(np.abs(imu.gyro[imu.time <= _frame_time(-3, claps) + 1e-12])) < 1e-5
    # the subject is moving during the trial: the accelerometer sees more than gravity there
    assert np.max(np.abs(np.linalg.norm(imu.accel, axis=-1) - 9.81)) > 5.0


def test_noise_and_bias(walk):
    noisy = simulate_imu(walk["skeleton"], walk["rig"], walk["motion"], FPS, walk["claps"], seed=4)
    exact, n = walk["imu"], walk["imu"].num_samples
    for name, sigma, bound in (("gyro", GYRO_NOISE, GYRO_BIAS), ("accel", ACCEL_NOISE, ACCEL_BIAS)):
        error = getattr(noisy, name) - getattr(exact, name)
        bias = error.mean(axis=0)  # (S, 3)
        assert np.all(np.abs(bias) <= bound + 5 * sigma / np.sqrt(n))
        assert np.std(bias) > 0.2 * bound  # biases differ between sensors and axes
        assert np.std(error - bias) == pytest.approx(sigma, rel=0.05)
    assert np.array_equal(noisy.camera_from_imu, exact.camera_from_imu)  # the mounts depend on the seed only
    again = simulate_imu(walk["skeleton"], walk["rig"], walk["motion"], FPS, walk["claps"], seed=4)
    other = simulate_imu(walk["skeleton"], walk["rig"], walk["motion"], FPS, walk["claps"], seed=4, trial_index=1)
    assert np.array_equal(again.gyro, noisy.gyro) and not np.array_equal(other.gyro, noisy.gyro)


def test_contacts_flag_stance_not_swing(walk):
    skeleton, motion, claps = walk["skeleton"], walk["motion"], walk["claps"]
    contacts = simulate_contacts(skeleton, motion, FPS, claps)
    assert contacts.segments == ("left_foot", "right_foot")
    assert np.array_equal(contacts.time, walk["imu"].time)
    joints = np.asarray(forward_kinematics(skeleton, motion).translation())[:, [skeleton.index(s) for s in contacts.segments]]
    speed = np.linalg.norm(joints[2:] - joints[:-2], axis=-1) * FPS / 2  # (T - 2, 2) at frames 1 .. T - 2
    height = joints[1:-1, :, 2] - joints[..., 2].min(axis=0)
    frames = np.arange(1, motion.num_frames - 1)
    flags = contacts.at(_frame_time(frames, claps))
    swing = speed > 0.5
    stance = (speed < 0.07) & (height < 0.03)
    assert swing.sum(axis=0).min() > 20 and stance.sum(axis=0).min() > 10
    assert not np.any(flags & swing)
    assert np.mean(flags[stance]) > 0.9
    fraction = contacts.in_contact.mean(axis=0)
    assert np.all((fraction > 0.15) & (fraction < 0.6))
    with pytest.raises(ValueError, match="no segment"):
        simulate_contacts(skeleton, motion, FPS, claps, segments=["left_toe"])


def test_integrate_gyro_on_an_analytic_rotation():
    """A fixed axis with angle θ(t) = 1 − cos(2πt) and a constant spin about another axis: closed forms."""
    rate = 200.0
    time = np.arange(0, 1.0 + 1e-9, 1 / rate)
    axis = np.array([0.6, 0.0, 0.8])
    gyro = (2 * np.pi * np.sin(2 * np.pi * time))[:, None, None] * axis
    t0, t1 = np.array([0.1, 0.2034, 0.0]), np.array([0.3, 0.7311, 1.0])
    rel = integrate_gyro(time, gyro, t0, t1)
    true = quat_exp(((np.cos(2 * np.pi * t0) - np.cos(2 * np.pi * t1)))[:, None, None] * axis)
    assert np.max(_angle(true, rel)) < 1e-7  # 0.3 to 1.3 rad
    spin = np.broadcast_to([0.0, 3.0, 0.0], (len(time), 2, 3))
    np.testing.assert_allclose(integrate_gyro(time, spin, 0.25, 0.75), quat_exp(np.broadcast_to([0, 1.5, 0], (2, 3))),
                               atol=1e-12)
    with pytest.raises(ValueError, match="within"):
        integrate_gyro(time, gyro, 0.5, 1.2)


def _imu_arrays(walk):
    imu = walk["imu"]
    return {"time": imu.time, "rate": np.float64(imu.rate), "cameras": np.array(imu.cameras),
            "camera_from_imu": imu.camera_from_imu, "gyro": imu.gyro, "accel": imu.accel}


def test_round_trip(walk, tmp_path):
    imu = walk["imu"]
    path = write_imu(tmp_path / "imu.npz", imu)
    back = read_imu(path)
    assert back.cameras == imu.cameras and back.rate == imu.rate
    for field in ("time", "camera_from_imu", "gyro", "accel"):
        assert np.array_equal(getattr(back, field), getattr(imu, field)) and getattr(back, field).dtype == np.float64
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    write_imu(path, imu)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == digest  # deterministic bytes

    contacts = simulate_contacts(walk["skeleton"], walk["motion"], FPS, walk["claps"])
    back = read_contacts(write_contacts(tmp_path / "contacts.npz", contacts))
    assert back.segments == contacts.segments and np.array_equal(back.in_contact, contacts.in_contact)
    assert np.array_equal(back.time, contacts.time) and back.in_contact.dtype == bool
    assert sorted(p.name for p in tmp_path.iterdir()) == ["contacts.npz", "imu.npz"]  # no temporary files left


def _corrupt(arrays, field, how):
    arrays = dict(arrays)
    if how == "missing":
        del arrays[field]
    elif how == "shape":
        arrays[field] = arrays[field][..., :-1] if arrays[field].ndim > 1 else np.atleast_1d(arrays[field])[:, None]
    elif how == "nan":
        arrays[field] = arrays[field].copy()
        arrays[field].flat[3] = np.nan
    elif how == "dtype":
        arrays[field] = arrays[field].astype(np.complex128) if arrays[field].dtype.kind != "U" else np.arange(len(arrays[field]))
    return arrays


IMU_CASES = [(f, "missing", "missing field") for f in ("time", "rate", "cameras", "camera_from_imu", "gyro", "accel")] + [
    ("time", "shape", "shape"), ("gyro", "shape", "shape"), ("accel", "shape", "shape"),
    ("camera_from_imu", "shape", "shape"), ("rate", "shape", "shape"),
    ("gyro", "nan", "non-finite"), ("accel", "nan", "non-finite"), ("time", "nan", "non-finite"),
    ("gyro", "dtype", "dtype"), ("time", "dtype", "dtype"), ("cameras", "dtype", "dtype"),
]


@pytest.mark.parametrize("field, how, message", IMU_CASES)
def test_imu_file_errors_name_the_file_and_field(walk, tmp_path, field, how, message):
    path = tmp_path / "imu.npz"
    np.savez(path, **_corrupt(_imu_arrays(walk), field, how))
    with pytest.raises(ValueError, match=rf"imu\.npz: field '{field}'.*{message}|imu\.npz: {message} '{field}'"):
        read_imu(path)


def test_imu_file_value_errors(walk, tmp_path):
    arrays = _imu_arrays(walk)
    path = tmp_path / "imu.npz"
    for change, message in (
        ({"time": arrays["time"][::-1].copy()}, "field 'time' is not strictly increasing"),
        ({"rate": np.float64(0.0)}, "field 'rate' must be positive"),
        ({"camera_from_imu": arrays["camera_from_imu"] * 2}, "field 'camera_from_imu' has quaternions"),
        ({"cameras": np.array(["a"] * len(arrays["cameras"]))}, "field 'cameras' has empty or repeated names"),
    ):
        np.savez(path, **{**arrays, **change})
        with pytest.raises(ValueError, match=f"imu.npz: {message}"):
            read_imu(path)
    path.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="imu.npz: not a readable .npz"):
        read_imu(path)
    with pytest.raises(ValueError, match="missing"):
        read_imu(tmp_path / "none.npz")
    bad = dataclasses.replace(walk["imu"], gyro=walk["imu"].gyro[:-1])
    with pytest.raises(ValueError, match=r"out\.npz: field 'gyro' has shape"):
        write_imu(tmp_path / "out.npz", bad)
    assert not (tmp_path / "out.npz").exists()


def test_contact_file_errors_name_the_file_and_field(tmp_path):
    good = {"time": np.arange(5) / 240.0, "segments": np.array(["left_foot", "right_foot"]),
            "in_contact": np.zeros((5, 2), bool)}
    path = tmp_path / "contacts.npz"
    cases = [({k: v for k, v in good.items() if k != field}, f"missing field '{field}'") for field in good] + [
        ({**good, "in_contact": np.zeros((5, 2), np.int64)}, "field 'in_contact' has dtype int64"),
        ({**good, "in_contact": np.zeros((4, 2), bool)}, "field 'in_contact' has shape"),
        ({**good, "segments": np.array(["left_foot"])}, "field 'in_contact' has shape"),
        ({**good, "time": np.array([0.0, 1.0, 1.0, 2.0, 3.0])}, "field 'time' is not strictly increasing"),
        ({**good, "time": np.array([0.0, 1.0, np.inf, 2.0, 3.0])}, "field 'time' has non-finite"),
        ({**good, "segments": np.array([1, 2])}, "field 'segments' has dtype"),
    ]
    for arrays, message in cases:
        np.savez(path, **arrays)
        with pytest.raises(ValueError, match=f"contacts.npz: {message}"):
            read_contacts(path)
    with pytest.raises(ValueError, match=r"c\.npz: field 'in_contact'"):
        write_contacts(tmp_path / "c.npz", ContactRecording(good["time"], ("left_foot",), good["in_contact"]))


def test_write_sensor_data_from_ground_truth(walk, tmp_path):
    """Only capture.json, the skeleton, the rig and the trials' ground truth are needed; files as simulate_* make."""
    from bcmocap.io.model_json import rig_to_dict, skeleton_to_dict
    from bcmocap.sim.studio import StudioSettings

    folder = tmp_path / "capture"
    (folder / "ground_truth").mkdir(parents=True)
    manifest = {"format": "bcmocap-capture", "version": 1, "settings": StudioSettings(seed=5).to_dict(), "trials": ["capture"]}
    (folder / "capture.json").write_text(json.dumps(manifest))
    skeleton, rig, motion = walk["skeleton"], walk["rig"], walk["motion"]
    (folder / "ground_truth" / "skeleton.json").write_text(json.dumps(skeleton_to_dict(skeleton)))
    (folder / "ground_truth" / "rig.json").write_text(json.dumps(rig_to_dict(rig, skeleton)))
    with pytest.raises(ValueError, match=r"capture\.npz: missing"):
        write_sensor_data(folder)
    np.savez(folder / "ground_truth" / "capture.npz", root_position=np.asarray(motion.root_position),
             rotations=np.asarray(motion.rotations), fps=np.float64(FPS), clap_frames=walk["claps"])
    written = write_sensor_data(folder)
    assert written == {"capture": (folder / "trials/capture/imu.npz", folder / "trials/capture/contacts.npz")}
    imu = read_imu(written["capture"][0])
    expected = simulate_imu(skeleton, rig, motion, FPS, walk["claps"], seed=5)
    assert np.array_equal(imu.gyro, expected.gyro) and np.array_equal(imu.accel, expected.accel)
    assert imu.time[-1] == pytest.approx((walk["claps"][1] - walk["claps"][0]) / FPS)
    contacts = read_contacts(written["capture"][1])
    assert np.array_equal(contacts.in_contact, simulate_contacts(skeleton, motion, FPS, walk["claps"]).in_contact)
    exact = write_sensor_data(folder, seed=4, **EXACT)
    assert np.array_equal(read_imu(exact["capture"][0]).gyro, walk["imu"].gyro)
    (folder / "capture.json").write_text(json.dumps({**manifest, "trials": ["../../elsewhere"]}))
    with pytest.raises(ValueError, match=r"capture\.json: trials\[0\] '\.\./\.\./elsewhere' is not a plain name"):
        write_sensor_data(folder)


@pytest.mark.slow
def test_capture_gets_sensor_files(tmp_path):
    """write_capture's static files include each trial's sensors, the bytes write_sensor_data writes."""
    from bcmocap.sim.studio import StudioSettings, _plan, _write_static_files

    settings = StudioSettings(seconds=2.0, rom_seconds=0.5, seed=2, width=32, height=18, reference_photos=2,
                              reference_width=32, reference_height=24, markers_per_segment=1)
    plan = _plan(settings)
    folder = tmp_path / "capture"
    for sub in ("intrinsics", "reference", "ground_truth", "trials/rom", "trials/capture"):
        (folder / sub).mkdir(parents=True)
    manifest = {"format": "bcmocap-capture", "version": 1, "settings": settings.to_dict(), "trials": ["rom", "capture"]}
    (folder / "capture.json").write_text(json.dumps(manifest))
    _write_static_files(folder, plan)
    before = {p: p.read_bytes() for p in folder.glob("trials/*/*.npz")}
    assert sorted(p.relative_to(folder).as_posix() for p in before) == [
        "trials/capture/contacts.npz", "trials/capture/imu.npz", "trials/rom/contacts.npz", "trials/rom/imu.npz"]
    for p in before:
        p.unlink()
    write_sensor_data(folder)
    assert all(p.read_bytes() == data for p, data in before.items())
    clap_frames = np.load(folder / "ground_truth" / "rom.npz")["clap_frames"]
    assert read_imu(folder / "trials" / "rom" / "imu.npz").time[-1] == pytest.approx(
        (clap_frames[1] - clap_frames[0]) / settings.fps)
