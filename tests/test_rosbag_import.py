"""``vtolpose import rosbag``: bags written by ``rosbags`` itself (sqlite3 and MCAP storage) from a simulated
flight import to the same files, and replay to the same trajectory, as the original dataset."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from vtolpose.config import load_config
from vtolpose.drivers.files.dataset import CAM_CSV, GPS_CSV, IMU_CSV, Dataset
from vtolpose.drivers.files.rosbag_import import BagImportError, import_rosbag
from vtolpose.drivers.files.tum import write_tum
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.drivers.simulator.render import default_camera
from vtolpose.service.cli import main
from vtolpose.service.replay.session import replay

ROS = get_typestore(Stores.ROS2_JAZZY)
T = ROS.types
A_ENU_NED = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])
A_FLU_FRD = np.diag([1.0, -1, -1])


def header(t_ns: int, frame: str):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t_ns // 10**9), nanosec=int(t_ns % 10**9)),
                                    frame_id=frame)


def vec(v, kind="geometry_msgs/msg/Vector3"):
    return T[kind](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def quat_xyzw(q_wxyz):
    return T["geometry_msgs/msg/Quaternion"](x=float(q_wxyz[1]), y=float(q_wxyz[2]), z=float(q_wxyz[3]), w=float(q_wxyz[0]))


def rot_to_quat(r):
    w = np.sqrt(max(1.0 + np.trace(r), 1e-12)) / 2
    return np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])


def rot(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def write_bag(dataset_root: Path, bag: Path, storage: StoragePlugin, compressed: bool, truth_type: str,
              imu_covariance: bool = False) -> None:
    """The dataset's raw streams as ROS 2 messages, stamped with the sensor times, written by rosbags."""
    ds = Dataset.open(dataset_root)
    imu = ds.imu_raw()
    gps_rows = [line.split(",") for line in (dataset_root / GPS_CSV).read_text().splitlines() if not line.startswith("#")]
    truth = ds.truth()
    noise, rate = ds.calibration.imu.noise, ds.calibration.imu.rate_hz
    var_g = np.diag(noise.gyro_noise_density**2 * rate).reshape(9) if imu_covariance else np.zeros(9)
    var_a = np.diag(noise.accel_noise_density**2 * rate).reshape(9) if imu_covariance else np.zeros(9)
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    with Writer(bag, version=9, storage_plugin=storage) as w:
        c_imu = w.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=ROS)
        c_gps = w.add_connection("/fix", "sensor_msgs/msg/NavSatFix", typestore=ROS)
        c_img = w.add_connection("/camera/image", image_type, typestore=ROS)
        c_truth = w.add_connection("/truth", truth_type, typestore=ROS)
        for t, g, a in zip(imu.t_ns.tolist(), imu.gyro, imu.accel):
            msg = T["sensor_msgs/msg/Imu"](
                header=header(t, "imu"), orientation=quat_xyzw([1.0, 0, 0, 0]), orientation_covariance=np.r_[-1.0, np.zeros(8)],
                angular_velocity=vec(g), angular_velocity_covariance=var_g, linear_acceleration=vec(a),
                linear_acceleration_covariance=var_a)
            w.write(c_imu, t + 5_000_000, ROS.serialize_cdr(msg, "sensor_msgs/msg/Imu"))  # received a little later
        for row in gps_rows:
            t, (lat, lon, alt, sh, sv) = int(row[0]), (float(x) for x in row[1:])
            msg = T["sensor_msgs/msg/NavSatFix"](
                header=header(t, "gps"), status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                latitude=lat, longitude=lon, altitude=alt, position_covariance=np.diag([sh**2, sh**2, sv**2]).reshape(9),
                position_covariance_type=2)
            w.write(c_gps, t, ROS.serialize_cdr(msg, "sensor_msgs/msg/NavSatFix"))
        unusable = T["sensor_msgs/msg/NavSatFix"](
            header=header(int(gps_rows[0][0]) + 1, "gps"), status=T["sensor_msgs/msg/NavSatStatus"](status=-1, service=1),
            latitude=0.0, longitude=0.0, altitude=0.0, position_covariance=np.zeros(9), position_covariance_type=0)
        w.write(c_gps, int(gps_rows[0][0]) + 1, ROS.serialize_cdr(unusable, "sensor_msgs/msg/NavSatFix"))
        for t, path in ds.camera_frames():
            image = ds.load_frame(path)
            if compressed:
                msg = T[image_type](header=header(t, "camera"), format="png",
                                    data=np.frombuffer(cv2.imencode(".png", image)[1].tobytes(), np.uint8))
            else:  # as a colour camera would send it: the importer turns it grey again
                bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
                msg = T[image_type](header=header(t, "camera"), height=bgr.shape[0], width=bgr.shape[1], encoding="bgr8",
                                    is_bigendian=0, step=bgr.shape[1] * 3, data=bgr.reshape(-1))
            w.write(c_img, t, ROS.serialize_cdr(msg, image_type))
        for t, p, q, v in zip(truth.t_ns.tolist(), truth.p, truth.q, truth.v):
            p_enu, r_enu = A_ENU_NED @ p, A_ENU_NED @ rot(q) @ A_FLU_FRD.T
            pose = T["geometry_msgs/msg/Pose"](position=vec(p_enu, "geometry_msgs/msg/Point"), orientation=quat_xyzw(rot_to_quat(r_enu)))
            if truth_type == "nav_msgs/msg/Odometry":
                twist = T["geometry_msgs/msg/Twist"](linear=vec(A_FLU_FRD @ rot(q).T @ v), angular=vec(np.zeros(3)))
                msg = T[truth_type](header=header(t, "map"), child_frame_id="base_link",
                                    pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                                    twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))
            else:
                msg = T[truth_type](header=header(t, "map"), pose=pose)
            w.write(c_truth, t, ROS.serialize_cdr(msg, truth_type))


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Path:
    return write_flight(simulate_flight("landfill", 8.0, 6), tmp_path_factory.mktemp("bag") / "landfill",
                        camera=default_camera())


def trajectory_bytes(root: Path, sensors: list[str], out: Path) -> bytes:
    result = replay(Dataset.open(root), load_config(), sensors)
    write_tum(out, result.trajectory.t_ns, result.trajectory.p, result.trajectory.q)
    return out.read_bytes()


@pytest.mark.parametrize("storage, compressed, truth_type", [
    (StoragePlugin.SQLITE3, False, "nav_msgs/msg/Odometry"),
    (StoragePlugin.MCAP, True, "geometry_msgs/msg/PoseStamped"),
])
def test_bag_imports_to_the_same_dataset_and_trajectory(flight, tmp_path, storage, compressed, truth_type):
    bag = tmp_path / "bag"
    write_bag(flight, bag, storage, compressed, truth_type)
    out = tmp_path / "imported"
    summary = import_rosbag(bag, out, "/imu/data", "/fix", "/camera/image", "/truth", flight / "dataset.yaml")
    assert summary["skipped"] == {"gps_no_fix": 1}
    for rel in (IMU_CSV, GPS_CSV, CAM_CSV):
        assert (out / rel).read_bytes() == (flight / rel).read_bytes(), rel
    original, imported = Dataset.open(flight), Dataset.open(out)
    for (t0, p0), (t1, p1) in zip(original.camera_frames(), imported.camera_frames()):
        assert t0 == t1 and np.array_equal(original.load_frame(p0), imported.load_frame(p1))
    truth0, truth1 = original.truth(), imported.truth()
    assert np.array_equal(truth0.t_ns, truth1.t_ns) and np.allclose(truth0.p, truth1.p, atol=1e-9)
    assert np.allclose(np.abs(np.sum(truth0.q * truth1.q, axis=1)), 1.0)  # same attitude (q or -q)
    v_tol = 1e-9 if truth_type.endswith("Odometry") else 0.05  # PoseStamped: velocity from position differences
    assert np.allclose(truth0.v, truth1.v, atol=v_tol)
    sensors = ["imu", "gps", "camera"] if compressed else ["imu", "gps"]
    assert trajectory_bytes(out, sensors, tmp_path / "b.txt") == trajectory_bytes(flight, sensors, tmp_path / "a.txt")


def test_without_a_calibration_the_bag_gives_mounting_and_noise(flight, tmp_path):
    bag = tmp_path / "bag"
    write_bag(flight, bag, StoragePlugin.MCAP, True, "nav_msgs/msg/Odometry", imu_covariance=True)
    out = tmp_path / "imported"
    assert main(["import", "rosbag", str(bag), "--imu", "/imu/data", "--gps", "/fix", "--out", str(out)]) == 0
    cal, want = Dataset.open(out).calibration, Dataset.open(flight).calibration
    assert np.allclose(cal.imu.R_BI, A_FLU_FRD)  # the IMU taken as base_link: FLU into FRD
    assert np.allclose(cal.imu.noise.gyro_noise_density, want.imu.noise.gyro_noise_density, rtol=1e-3)
    assert np.allclose(cal.imu.noise.accel_noise_density, want.imu.noise.accel_noise_density, rtol=1e-3)
    assert cal.camera is None and not (out / CAM_CSV).exists()


def test_bag_errors_name_the_topic(flight, tmp_path, capsys):
    bag = tmp_path / "bag"
    write_bag(flight, bag, StoragePlugin.SQLITE3, False, "nav_msgs/msg/Odometry")
    with pytest.raises(BagImportError, match=r"--imu /imu: no such topic in the bag; it has .*/imu/data \(sensor_msgs/msg/Imu\)"):
        import_rosbag(bag, tmp_path / "a", "/imu", "/fix", calibration_file=flight / "dataset.yaml")
    with pytest.raises(BagImportError, match=r"--gps /imu/data: is sensor_msgs/msg/Imu, expected sensor_msgs/msg/NavSatFix"):
        import_rosbag(bag, tmp_path / "b", "/imu/data", "/imu/data", calibration_file=flight / "dataset.yaml")
    with pytest.raises(BagImportError, match="no rate/acceleration covariance"):
        import_rosbag(bag, tmp_path / "c", "/imu/data", "/fix")
    with pytest.raises(BagImportError, match="--image /camera/image: frames need the camera's calibration"):
        import_rosbag(bag, tmp_path / "d", "/imu/data", "/fix", image_topic="/camera/image")
    assert main(["import", "rosbag", str(bag), "--imu", "/imu/data", "--out", str(tmp_path / "e")]) == 1
    assert "needs --imu TOPIC and --gps TOPIC" in capsys.readouterr().err
    summary_out = tmp_path / "f"
    assert main(["import", "rosbag", str(bag), "--imu", "/imu/data", "--gps", "/fix", "--out", str(summary_out),
                 "--calibration", str(flight / "dataset.yaml")]) == 0
    assert f"gps fixes: {len(Dataset.open(flight).gps().t_ns)}\n" in capsys.readouterr().out
