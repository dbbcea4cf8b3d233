"""``vtolpose export``: a replayed TUM trajectory as a WGS84 path (GeoJSON, KML) with time and quality per
point; positions round-trip to NED around the dataset's origin, quality comes from the same run's MCAP."""

import json
import xml.etree.ElementTree as ET

import numpy as np
import pymap3d
import pytest

from vtolpose.drivers.files.dataset import Dataset
from vtolpose.drivers.files.survey import read_recorded_estimates
from vtolpose.drivers.files.tum import read_tum
from vtolpose.drivers.simulator import simulate_flight
from vtolpose.drivers.simulator.export import write_flight
from vtolpose.service.cli import main

KML_NS = {"k": "http://www.opengis.net/kml/2.2"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    data = write_flight(simulate_flight("landfill", 12.0, 3), root / "landfill")
    assert main(["-q", "replay", str(data), "--sensors", "imu,gps", "--out", str(root / "traj.txt"),
                 "--mcap", str(root / "flight.mcap"), "--no-progress"]) == 0
    return root, data


def test_geojson_points_round_trip_with_recorded_quality(run, capsys):
    root, data = run
    out = root / "path.geojson"
    assert main(["export", str(root / "traj.txt"), "--dataset", str(data), "--quality", str(root / "flight.mcap"),
                 "--geojson", str(out), "--step", "0"]) == 0
    assert "matched in" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    line, points = doc["features"][0], doc["features"][1:]
    t_ns, p_ned, _ = read_tum(root / "traj.txt")
    assert line["geometry"]["type"] == "LineString" and len(points) == len(t_ns)
    origin = Dataset.open(data).gps().origin_lla
    assert line["properties"]["origin_lat_lon_alt"] == list(origin) and line["properties"]["quality_source"]
    lon, lat, alt = np.array([f["geometry"]["coordinates"] for f in points]).T
    back = np.column_stack(pymap3d.geodetic2ned(lat, lon, alt, *origin))
    assert np.allclose(back, p_ned, atol=2e-3)  # 1e-9° and 0.1 mm rounding in the file
    assert [round(f["properties"]["t_s"] * 1e9) for f in points[:50]] == t_ns[:50].tolist()
    recorded = read_recorded_estimates(root / "flight.mcap")
    by_t = dict(zip(recorded.t_ns.tolist(), range(len(recorded.t_ns))))
    same_instant = [(f["properties"], by_t[t]) for f, t in zip(points, t_ns.tolist()) if t in by_t]
    assert len(same_instant) > 0.9 * len(points)
    for props, j in same_instant[::97]:
        assert props["quality"] == recorded.quality[j] and props["status"] == recorded.status[j]
        assert props["sigma_h_m"] == pytest.approx(recorded.sigma_h_m[j], abs=1e-4)
    assert max(p["properties"]["quality"] or 0 for p in points) > 50
    assert all(p["properties"]["sigma_h_m"] >= 0 for p in points if p["properties"]["sigma_h_m"] is not None)


def test_kml_has_the_path_and_thinned_points(run):
    root, data = run
    out = root / "path.kml"
    assert main(["export", str(root / "traj.txt"), "--dataset", str(data), "--quality", str(root / "flight.mcap"),
                 "--kml", str(out), "--step", "1"]) == 0
    tree = ET.parse(out)
    coords = tree.find(".//k:LineString/k:coordinates", KML_NS).text.split()
    placemarks = tree.findall(".//k:Folder/k:Placemark", KML_NS)
    t_ns, _, _ = read_tum(root / "traj.txt")
    span_s = (t_ns[-1] - t_ns[0]) * 1e-9
    assert len(coords) == len(placemarks) and int(span_s) <= len(placemarks) <= int(span_s) + 2
    data_fields = {d.get("name"): d.find("k:value", KML_NS).text for d in placemarks[-1].findall(".//k:Data", KML_NS)}
    assert set(data_fields) == {"t_s", "quality", "sigma_h_m", "sigma_v_m", "status"} and int(data_fields["quality"]) > 0
    lon, lat, alt = (float(x) for x in coords[0].split(","))
    assert abs(lat - Dataset.open(data).gps().origin_lla[0]) < 0.01


def test_without_quality_and_origin_errors(run, tmp_path, capsys):
    root, data = run
    out = tmp_path / "p.geojson"
    assert main(["export", str(root / "traj.txt"), "--origin", "58.43,15.68,60", "--geojson", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["features"][0]["properties"]["quality_source"] is None
    assert {f["properties"]["quality"] for f in doc["features"][1:]} == {None}
    # the recording's own origin serves when no other is given
    assert main(["export", str(root / "traj.txt"), "--quality", str(root / "flight.mcap"), "--geojson", str(out)]) == 0
    assert "origin from recording" in capsys.readouterr().out
    assert main(["export", str(root / "traj.txt"), "--geojson", str(out)]) == 1
    assert "give --dataset DIR or --origin" in capsys.readouterr().err
    assert main(["export", str(root / "traj.txt"), "--origin", "91,0,0", "--geojson", str(out)]) == 1
    assert main(["export", str(root / "traj.txt"), "--origin", "1,2,3"]) == 1
    assert "nothing to write" in capsys.readouterr().err
