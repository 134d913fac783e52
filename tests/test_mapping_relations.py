"""Relative-pose ground truth (Kümmerle et al. 2009 relations): reading, clock offset,
error; and ``cgamap map build --relations``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cgamap.daemon.cli import main
from cgamap.mapping.evaluation import clock_offset, load_relations, relations_error
from cgamap.mapping.odometry import relative
from conftest import require_data


def _write(path, rows):
    path.write_text("".join(" ".join(f"{v:.6f}" for v in r) + "\n" for r in rows))
    return path


def _trajectory(n=60, seed=0):
    rng = np.random.default_rng(seed)
    stamps = np.cumsum(rng.uniform(0.5, 1.5, n))
    poses = np.cumsum(rng.normal(0, [0.3, 0.3, 0.2], (n, 3)), axis=0)
    return stamps, poses


def _relations_of(stamps, poses, pairs, offset):
    r = relative(poses[pairs[:, 0]], poses[pairs[:, 1]])
    z = np.zeros(len(pairs))
    return np.column_stack([stamps[pairs[:, 0]] + offset, stamps[pairs[:, 1]] + offset,
                            r[:, 0], r[:, 1], z, z, z, r[:, 2]])


def test_offset_and_error_of_a_known_trajectory(tmp_path):
    stamps, poses = _trajectory()
    rng = np.random.default_rng(1)
    pairs = np.sort(rng.choice(60, (80, 2)), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    off = 976052857.3371
    rel = load_relations(_write(tmp_path / "r.relations",
                                _relations_of(stamps, poses, pairs, off)))
    assert clock_offset(stamps, rel[:, :2].ravel()) == pytest.approx(off, abs=1e-3)
    exact = relations_error(stamps, poses, rel)
    assert exact["relations"] == len(pairs)
    assert exact["trans_mean_m"] < 1e-5 and exact["rot_mean_deg"] < 1e-3
    # a pose moved by 0.1 m shows up in the relations that touch it, and only there
    k = int(pairs[0, 1])
    moved = poses.copy()
    moved[k, :2] += 0.1 * np.array([np.cos(moved[k, 2]), np.sin(moved[k, 2])])
    err = relations_error(stamps, moved, rel)
    touching = np.sum((pairs == k).any(axis=1))
    assert touching >= 1
    assert err["trans_mean_m"] == pytest.approx(0.1 * touching / len(pairs), rel=0.02)
    # relations at instants that are not scans are left out
    rel2 = rel.copy()
    rel2[:5, 0] += 0.5
    assert relations_error(stamps, poses, rel2, offset=off)["relations"] == len(pairs) - 5


@pytest.mark.parametrize("text, what", [
    ("1 2 3\n", "3 fields"),
    ("1 2 3 4 5 6 7 x\n", "not a relation"),
    ("1 2 3 4 5 6 7 nan\n", "non-finite"),
    ("# only a comment\n", "no relations"),
])
def test_malformed_relations_name_the_line(tmp_path, text, what):
    p = tmp_path / "bad.relations"
    p.write_text("0 1 0 0 0 0 0 0\n" + text if "comment" not in text else text)
    with pytest.raises(ValueError) as e:
        load_relations(p)
    assert what in str(e.value)
    if "comment" not in text:
        assert "bad.relations:2" in str(e.value)


def test_cli_build_with_relations(tmp_path, capsys):
    log = require_data("laser/intel-corrected.log.gz")
    rel = require_data("laser/intel.relations")
    out = tmp_path / "m"
    assert main(["map", "build", "--log", str(log), "--out", str(out), "--quiet",
                 "--odom-noise", "high", "--relations", str(rel)]) == 0
    r = json.loads((out / "report.json").read_text())["relations"]
    est, ref, odo = r["estimate"], r["reference"], r["odometry"]
    assert est["relations"] >= 30 and est["relations"] == ref["relations"]
    # measured: estimate 0.045 m / 0.87 deg mean, the log's own reference 0.044 m / 0.68 deg,
    # the corrupted odometry 5.6 m / 22 deg
    assert est["trans_mean_m"] < 2 * ref["trans_mean_m"]
    assert est["trans_mean_m"] < 0.1 * odo["trans_mean_m"]
    capsys.readouterr()
    assert main(["map", "build", "--log", str(log), "--out", str(out), "--quiet",
                 "--relations", str(tmp_path / "none.relations")]) == 2
    assert "--relations" in capsys.readouterr().err
