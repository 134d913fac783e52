"""The daemon's plane map is always mapping.planemap.PlaneMap; a checkpoint from a build that
used the stand-in map (``map3d: {"simple": [...]}``) migrates into it on load."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from cgamap.daemon import config as config_mod
from cgamap.daemon.loop import MappingLoop
from cgamap.daemon.store import CheckpointStore, encode_checkpoint
from cgamap.mapping.planemap import PlaneMap as MappingPlaneMap

FLOOR = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 2.0, 0.0], [0.0, 2.0, 0.0]])
WALL = np.array([[4.0, 0.0, 0.0], [4.0, 2.0, 0.0], [4.0, 2.0, 2.5], [4.0, 0.0, 2.5]])


def simple_entries(as_arrays: bool) -> list[dict]:
    conv = np.asarray if as_arrays else (lambda a: np.asarray(a).tolist())
    return [
        {"normal": conv([0.0, 0.0, 1.0]), "rho": 0.0, "area": 6.0, "corners": conv(FLOOR),
         "observations": 5},
        {"normal": conv([1.0, 0.0, 0.0]), "rho": 4.0, "area": 5.0, "corners": conv(WALL),
         "observations": 2},
    ]


def loop() -> MappingLoop:
    return MappingLoop(config_mod.validate({"mapping": {"map3d": True, "map2d": False}}))


@pytest.mark.parametrize("as_arrays", [True, False], ids=["store-encoded", "plain-json"])
def test_simple_checkpoint_migrates_into_the_plane_map(tmp_path, as_arrays):
    # a checkpoint as the stand-in map wrote it, through the store's own encoding
    payload = {"pose": [1.0, 2.0, 0.5], "map2d": None, "counts": {"frames": 7},
               "map3d": {"simple": simple_entries(as_arrays)}}
    (tmp_path / "checkpoint.json").write_bytes(encode_checkpoint(payload))
    st = CheckpointStore(tmp_path).load()
    assert "simple" in st["map3d"]

    lp = loop()
    lp.load_state(st)
    planes = lp.planes.planes
    assert isinstance(lp.planes.m, MappingPlaneMap) and len(planes) == 2
    assert [p.id for p in planes] == [0, 1]
    assert np.allclose(planes[0].normal, [0, 0, 1]) and planes[0].rho == pytest.approx(0.0)
    assert np.allclose(planes[1].normal, [1, 0, 0]) and planes[1].rho == pytest.approx(4.0)
    assert [p.observations for p in planes] == [5, 2]
    assert planes[0].area == pytest.approx(6.0) and planes[1].area == pytest.approx(5.0)
    assert np.allclose(planes[1].corners, WALL)

    listed = lp.map_json()["planes"]
    assert [d["observations"] for d in listed] == [5, 2]
    assert all("extent" not in d and "cga" not in d for d in listed)

    # the next checkpoint is in the real map's layout and loads back the same
    out = CheckpointStore(tmp_path / "next")
    out.save(lp.state())
    st2 = out.load()
    assert set(st2["map3d"]) == {"planemap"}
    lp2 = loop()
    lp2.load_state(st2)
    assert [d["rho"] for d in lp2.map_json()["planes"]] == [d["rho"] for d in listed]

    # migrated planes merge with new observations like any map plane
    seen = SimpleNamespace(normal=np.array([0.0, 0.0, 1.0]), rho=0.01,
                           extent=FLOOR + [1.0, 0.5, 0.01], inliers=100)
    lp2.planes.integrate([seen])
    assert len(lp2.planes.planes) == 2 and lp2.planes.planes[0].observations == 6


def test_empty_or_missing_map3d_starts_empty():
    lp = loop()
    lp.load_state({"pose": [0, 0, 0], "map3d": {"simple": []}})
    assert lp.planes.planes == [] and lp.map_json()["configurations"] == []
    lp.load_state({"pose": [0, 0, 0]})
    assert lp.planes.state() == {"planemap": MappingPlaneMap().to_dict()}
