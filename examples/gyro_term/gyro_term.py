"""A gyroscope term (docs/residual-terms.md): each camera's turn between solver frames is what its gyro measured."""
import jax.numpy as jnp
import numpy as np

from bcmocap import SO3, TermWindow, residual_term
from bcmocap.io.sensors import integrate_gyro, read_imu


@residual_term(frames=2)
def gyro_turn(states, data, variables):
    turn = states[0].world_from_camera.rotation().inverse() @ states[1].world_from_camera.rotation()
    return (SO3(data["turn"]).inverse() @ turn).log(), data["valid"]  # rad, 3 per camera


def gyroscope(window: TermWindow, weight: float = 1e6):
    imu = read_imu(window.trial_file("imu.npz"))  # time (N,) s from the first clap, gyro (N, S, 3) rad/s
    t1 = window.times
    t0 = t1 - 1.0 / window.fps
    valid = (t0 >= imu.time[0]) & (t1 <= imu.time[-1])
    turn = integrate_gyro(imu.time, imu.gyro, np.where(valid, t0, imu.time[0]), np.where(valid, t1, imu.time[0]))
    mount = SO3(jnp.asarray(imu.camera_from_imu[:, :4]))  # each IMU's rotation in its camera
    turn = np.asarray((mount @ SO3(jnp.asarray(turn)) @ mount.inverse()).wxyz)  # (W, S, 4), in the cameras' frames
    cameras = [imu.cameras.index(name) for name in window.rig.names]
    return gyro_turn({"turn": turn[:, cameras], "valid": np.repeat(valid[:, None], len(cameras), 1)}, weight=weight)
