"""Dynamic tracks that annotation jitter cannot fool (issue 26), against the generator's truth.

The generator's parked cars carry annotation jitter like the real AV2 sample's (a returning walk of
0.1-1.5 m peak, heading a few degrees); long logs add a creeper (0.5 m/s for 8 s), a car that drives
6 m and parks, and one that waits 10 s and drives off. The truth per track is how far its true box
moved while it was annotated: 0 (static), at least 4 m (dynamic), or in between: a fast car seen for
under a second at the log's ends or the annotation radius, which no box rule can tell from jitter
(the issue leaves 2-4 m open too). Those are counted, and must stay rare; they are not scored.
The real sample's test is in ``test_convert_real.py``; the rule's unit tests in ``test_consumers.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import Converted, component_meta, synth_and_convert
from ncore.data.v4 import CuboidsComponent, PosesComponent

from ncore_convert import contract
from ncore_convert.converters.argoverse2 import Argoverse2Options
from ncore_convert.synth.argoverse2 import SynthConfig, annotated_boxes
from ncore_convert.synth.scene import Box, make_scene
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.objects import dynamic
from ncore_convert.transforms.objects.classes import AV2_TO_NCORE
from ncore_convert.transforms.objects.dynamic import TrackObservations, classify_tracks

MOVES_M = 4.0 - 1e-6  #: a truly moving track moved at least this far while annotated (the creeper: 4 m)
UNITS = ("up_lidar", "down_lidar")


def _annotation_stream(seed: int, seconds: float) -> tuple[list[Box], TrackObservations, list[str], dict[str, float]]:
    """The generator's scene and its annotations at 10 Hz in the city frame, their NCore classes,
    and per track the true distance moved between its first and last annotation."""
    scene = make_scene(np.random.default_rng(seed), seconds, np.random.default_rng([seed, 1]))
    ids, times_us, poses, dims, classes = [], [], [], [], []
    for k in range(int(round(seconds * 10))):
        t_s = k * 0.1
        for box, _ in annotated_boxes(scene, t_s, invert_se3(scene.ego.T_ego_city(np.array([t_s]))[0])):
            ids.append(box.track_uuid)
            times_us.append(k * 100_000)
            poses.append(box.T_annotated_city(t_s))
            dims.append(box.dims_m)
            classes.append(AV2_TO_NCORE[box.category])
    T = np.array(poses)
    observations = TrackObservations(ids, np.array(times_us), T[:, :3, 3], T[:, :3, :3], np.array(dims))
    by_id = {b.track_uuid: b for b in scene.boxes}
    spans: dict[str, list[float]] = {}
    for track, t_us in zip(ids, times_us, strict=True):
        spans.setdefault(track, []).append(t_us * 1e-6)
    moved = {t: by_id[t].moved_m(min(s), max(s)) for t, s in spans.items()}
    return scene.boxes, observations, classes, moved


def test_track_decisions_on_the_generators_traffic():
    """10 seeds of 15 s: every track decided as its truth says (precision and recall >= 0.99 asked;
    pedestrians are dynamic by class). The trap is real: a speed rule at 1 km/h over 1 s would call
    parked cars dynamic, as it did on real AV2 annotations."""
    tp = fp = fn = tn = gray = 0
    parked_fast = parked = slow_movers = 0
    for seed in range(10):
        boxes, observations, classes, moved = _annotation_stream(seed, 15.0)
        category = {b.track_uuid: b.category for b in boxes}
        decided = classify_tracks(observations, classes)
        for track, distance in moved.items():
            pedestrian = category[track] == "PEDESTRIAN"  # walks at any speed: dynamic by class
            if not pedestrian and 0.0 < distance < MOVES_M:
                gray += 1
                continue
            truly = distance >= MOVES_M or pedestrian
            said = decided[track].dynamic
            tp, fp, fn, tn = (
                tp + (truly and said),
                fp + (said and not truly),
                fn + (truly and not said),
                tn + (not truly and not said),
            )
            if category[track] == "REGULAR_VEHICLE" and distance == 0.0:
                rows = np.flatnonzero(np.asarray(observations.track_ids) == track)
                centres = observations.centers_m[rows]
                parked += 1
                parked_fast += bool(
                    len(rows) > 10 and np.linalg.norm(centres[10:] - centres[:-10], axis=1).max() > 1 / 3.6
                )
            slow_movers += category[track] == "REGULAR_VEHICLE" and MOVES_M <= distance <= 6.0 + 1e-6
    assert tp / (tp + fp) >= 0.99 and tp / (tp + fn) >= 0.99, (tp, fp, fn, tn)
    assert tn >= 150 and tp >= 200 and slow_movers >= 20, (tn, tp, slow_movers)
    assert gray <= 0.02 * (tp + fp + fn + tn), gray
    assert parked_fast >= 0.2 * parked, (parked_fast, parked)


@pytest.fixture(scope="module")
def long_log(tmp_path_factory) -> Converted:
    """13 s with the slow traffic (lidar and annotations, no cameras), converted with the defaults."""
    config = SynthConfig(seconds=13.0, seed=3, camera_fps=0, keep_truth=True)
    return synth_and_convert(
        Path(tmp_path_factory.mktemp("long")), config, Argoverse2Options(split="val", camera_ids=())
    )


def _by_truth(run: Converted) -> tuple[dict[str, Box], set[str]]:
    """The annotated tracks that truly moved (or are pedestrians), by id; and the gray ones (see the
    module docstring)."""
    annotated: dict[str, list[float]] = {}
    for obs in run.loader.get_cuboid_track_observations():
        annotated.setdefault(obs.track_id, []).append((obs.timestamp_us * 1000 - run.truth.t0_ns) * 1e-9)
    moved = {
        b.track_uuid: b.moved_m(min(annotated[b.track_uuid]), max(annotated[b.track_uuid]))
        for b in run.truth.scene.boxes
        if b.track_uuid in annotated
    }
    boxes = {b.track_uuid: b for b in run.truth.scene.boxes}
    truly = {t: boxes[t] for t, d in moved.items() if d >= MOVES_M or boxes[t].category == "PEDESTRIAN"}
    return truly, {t for t, d in moved.items() if 0.0 < d < MOVES_M and t not in truly}


def test_the_written_tracks_and_static_poses_on_a_long_log(long_log):
    """The converter's cuboid metadata: the dynamic tracks are the truly moving ones (slow traffic
    included); every other track has a static pose, the median of its jittering boxes, closer to the
    true box than a typical single annotation."""
    meta = component_meta(long_log.loader, CuboidsComponent, "default")
    truly, gray = _by_truth(long_log)
    slow = {t for t, b in truly.items() if b.category == "REGULAR_VEHICLE" and np.isfinite(b.move_from_s)}
    written = set(meta[contract.DYNAMIC_TRACKS])
    assert set(truly) <= written <= set(truly) | gray and len(slow) == 3 and len(gray) <= 1, (gray, slow)
    static = meta[contract.STATIC_POSES]
    annotated = set(meta[contract.SOURCE_CLASS_BY_TRACK])
    assert static["frame"] == "world" and set(static["tracks"]) == annotated - written
    T_world_global = (
        long_log.reader.open_component_readers(PosesComponent.Reader)["default"]
        .get_static_pose("world", "world_global")
        .astype(np.float64)
    )  # world_global is the city frame (localized)
    T_city_world = invert_se3(T_world_global)
    pose_errors, observation_errors = [], []
    for box in long_log.truth.scene.boxes:
        if box.jitter is None or box.track_uuid not in static["tracks"]:
            continue
        true_world = T_city_world[:3, :3] @ box.center0_m + T_city_world[:3, 3]
        error = np.linalg.norm(np.array(static["tracks"][box.track_uuid]["centroid"]) - true_world)
        peak = np.linalg.norm(box.jitter.offset_m, axis=1).max()
        assert error <= peak * np.sqrt(2) + 0.01, (box.track_uuid, error, peak)
        pose_errors.append(error)
        observation_errors.append(np.median(np.linalg.norm(box.jitter.offset_m, axis=1)))
    assert len(pose_errors) >= 10 and np.median(pose_errors) < np.median(observation_errors)


def test_dynamic_flag_on_a_long_log_with_jitter(long_log):
    """Points that hit a truly moving object: recall >= 0.99. Points on jittering parked cars: none
    flagged, but for those within a true mover's grown box (the rule's 0.5 m margin, plus the
    mover's own annotation jitter of at most 0.3 m + noise)."""
    truth = long_log.truth
    boxes = truth.scene.boxes
    truly, _ = _by_truth(long_log)
    is_moving = np.array([b.track_uuid in truly for b in boxes])
    is_parked = np.array([b.jitter is not None and not np.any(b.velocity_mps) for b in boxes])
    hits = hit_flagged = parked_hits = parked_flagged = unexplained = 0
    for unit_index, unit in enumerate(UNITS):
        source = long_log.loader.get_point_clouds_source(unit)
        for i, sweep in enumerate(truth.sweeps):
            flag = source.get_pc_generic_data(i, "dynamic_flag").astype(bool)
            rows = sweep.unit == unit_index
            index = sweep.box_index[rows]
            on_moving = (index >= 0) & is_moving[index]
            on_parked = (index >= 0) & is_parked[index]
            hits, hit_flagged = hits + on_moving.sum(), hit_flagged + (on_moving & flag).sum()
            parked_hits, parked_flagged = parked_hits + on_parked.sum(), parked_flagged + (on_parked & flag).sum()
            suspect = np.flatnonzero(on_parked & flag)
            if len(suspect):
                t_s = (sweep.time_ns[rows][suspect] - truth.t0_ns) * 1e-9
                T = truth.scene.ego.T_ego_city(t_s) @ truth.T_sensor_ego[unit]
                xyz = sweep.direction_sensor[rows][suspect] * sweep.distance_m[rows][suspect, None]
                xyz_city = np.einsum("nij,nj->ni", T[:, :3, :3], xyz) + T[:, :3, 3]
                near_mover = np.zeros(len(suspect), dtype=bool)
                for box in truly.values():
                    local = (xyz_city - box.center_m(t_s)) @ box.rotation
                    near_mover |= np.all(np.abs(local) <= box.dims_m / 2 + dynamic.BOX_MARGIN_M + 0.4, axis=1)
                unexplained += int((~near_mover).sum())
    assert hits > 5000 and hit_flagged / hits >= 0.99, (hit_flagged, hits)
    assert parked_hits > 50000 and unexplained == 0, (parked_flagged, parked_hits, unexplained)


def test_solid_boxes_place_static_tracks_at_their_median_and_moving_ones_at_the_time():
    """The occluders of ``--lidar-rgb``: a parked car whose annotations jitter sits at its median box
    at any time; a car driving at 10 m/s sits where its boxes are at that time, interpolated, and only
    while it is observed (up to ``HOLD_S`` beyond its ends)."""
    rng = np.random.default_rng(0)
    times_us = np.arange(0, 1_000_001, 100_000)
    parked = np.array([10.0, 5.0, 0.8]) + np.c_[rng.normal(0.0, 0.3, (len(times_us), 2)), np.zeros(len(times_us))]
    driving = np.array([[0.0, -3.0, 0.8]]) + np.outer(times_us[:4] * 1e-6, [10.0, 0.0, 0.0])
    observations = TrackObservations(
        ["parked"] * len(times_us) + ["driving"] * 4,
        np.r_[times_us, times_us[:4]],
        np.r_[parked, driving],
        np.tile(np.eye(3), (len(times_us) + 4, 1, 1)),
        np.tile([4.5, 1.9, 1.6], (len(times_us) + 4, 1)),
    )
    static = dynamic.static_poses(observations, {"parked"})
    solids = dynamic.SolidBoxes.select(observations, static, {"driving"}, kinds={"parked": 0, "driving": 0})
    T, half, velocity_mps, kind = solids.solids_at(150_000)
    assert len(T) == 2
    np.testing.assert_allclose(T[0, :3, 3], np.median(parked, axis=0))
    np.testing.assert_allclose(T[1, :3, 3], [1.5, -3.0, 0.8])
    np.testing.assert_allclose(half, [[2.25, 0.95, 0.8]] * 2)
    np.testing.assert_allclose(velocity_mps, [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]], atol=1e-9)
    np.testing.assert_array_equal(kind, [0, 0])
    T_late, *_ = solids.solids_at(300_000 + round(dynamic.HOLD_S * 1e6) + 1)
    assert len(T_late) == 1 and np.allclose(T_late[0], T[0])
    # an object whose kind hides nothing through its box (a sign, a cone) is no occluder
    no_kind = dynamic.SolidBoxes.select(observations, static, {"driving"}, kinds={"driving": 0})
    T_one, *_ = no_kind.solids_at(150_000)
    assert len(T_one) == 1 and np.allclose(T_one[0], T[1])


def test_dynamic_boxes_at_a_time_equal_each_tracks_own_interpolation():
    """``DynamicBoxes.at`` (all tracks in one pass) against :func:`_centres_at` track by track, on
    random tracks of 1 to 6 observations, at times before, inside and after them."""
    rng = np.random.default_rng(3)
    ids, times, centres = [], [], []
    for k in range(40):
        n = int(rng.integers(1, 7))
        ids += [f"t{k}"] * n
        times.append(np.sort(rng.choice(np.arange(0, 3_000_000, 50_000), n, replace=False)))
        centres.append(rng.normal(0.0, 20.0, (n, 3)))
    n_all = len(ids)
    observations = TrackObservations(
        ids, np.concatenate(times), np.concatenate(centres), np.tile(np.eye(3), (n_all, 1, 1)), np.ones((n_all, 3))
    )
    boxes = dynamic.DynamicBoxes.select(observations, set(ids))
    hold_us = round(dynamic.HOLD_S * 1e6)
    for t_us in rng.integers(-400_000, 3_400_000, 60).tolist() + [0, 2_950_000]:
        tracks, at_centres, nearest = boxes.at(t_us)
        expected = []
        for k in range(len(boxes)):
            a, b = int(boxes.bounds[k]), int(boxes.bounds[k + 1])
            track_times = boxes.timestamps_us[a:b]
            if track_times[0] - hold_us <= t_us <= track_times[-1] + hold_us:
                centre, near = dynamic._centres_at(track_times, boxes.centers_m[a:b], np.array([t_us]))
                expected.append((k, centre[0], a + int(near[0])))
        assert tracks.tolist() == [e[0] for e in expected]
        np.testing.assert_allclose(at_centres.reshape(-1, 3), np.reshape([e[1] for e in expected], (-1, 3)), atol=1e-9)
        assert nearest.tolist() == [e[2] for e in expected]
