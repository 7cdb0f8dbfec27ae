"""What moves, from the lidar alone (issue 53, ``transforms.lidar.free_space``; docs/motion.md).

- The bracket test on a lidar whose returns are known exactly (a wall and the street): a place is
  seen through only where all four rays around it ended beyond it.
- A converted synthetic TbV log (``--dynamic-source`` lidar, its default without annotations),
  scored per point against the generator's truth (the object each return hit, and whether it moved
  faster than 0.2 m/s then), read back as 3DGRUT reads it; a planted control (the flags flipped)
  fails the same bounds.
- The real AV2 sample with ``--dynamic-source lidar``: no point of a standing track's box is flagged.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import AV2_SAMPLE_LOG, component_meta, open_sequence
from ncore.data.v4 import CuboidsComponent, LidarSensorComponent
from ncore.impl.common.transformations import is_within_3d_bboxes
from upath import UPath

from ncore_convert import contract
from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
from ncore_convert.converters.argoverse2.convert import _sweeps as label_sweeps
from ncore_convert.converters.argoverse2.plan import plan_log
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.reader import Reader
from ncore_convert.synth.argoverse2 import SynthConfig, write_log
from ncore_convert.synth.raycast import cast_rays
from ncore_convert.transforms.lidar import free_space, motion_window, vlp32c
from ncore_convert.transforms.objects.dynamic import BOX_MARGIN_M
from ncore_convert.validate.readback import world_points

LIDAR_M = np.array([0.0, 0.0, 2.0])  #: the analytic lidar's place
WALL_X_M = 20.0  #: a wall across its view, x = 20 m; the street is z = 0


def _analytic_sweep() -> free_space.SweepSight:
    """A VLP-32C's rows and 0.2 degree columns from ``LIDAR_M``, returns on the street (z = 0) and on the
    wall (x = ``WALL_X_M``, |y| < 10 m, up to 6 m), whichever each ray meets first; none elsewhere."""
    elevation = np.radians(vlp32c.BEAM_ELEVATION_DEG)
    azimuth = np.radians(np.arange(-180.0, 180.0, 0.2) + 0.1)
    el, az = (a.ravel() for a in np.meshgrid(elevation, azimuth, indexing="ij"))
    beam = np.repeat(np.arange(len(elevation)), len(azimuth))
    direction = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        to_street = np.where(direction[:, 2] < 0, -LIDAR_M[2] / direction[:, 2], np.inf)
        to_wall = np.where(direction[:, 0] > 0, (WALL_X_M - LIDAR_M[0]) / direction[:, 0], np.inf)
        on_wall = LIDAR_M + direction * to_wall[:, None]
    to_wall = np.where((np.abs(on_wall[:, 1]) < 10.0) & (on_wall[:, 2] < 6.0), to_wall, np.inf)
    distance = np.minimum(to_street, to_wall)
    hit = np.isfinite(distance) & (distance < 200.0)
    points = LIDAR_M + direction[hit] * distance[hit, None]
    return free_space.SweepSight(points, np.broadcast_to(LIDAR_M, points.shape), beam[hit])


def test_a_place_is_seen_through_only_where_all_four_rays_around_it_ended_beyond_it():
    sight = _analytic_sweep()
    places = np.array(
        [
            [10.0, 0.3, 1.0],  # in the air between the lidar and the wall: seen through
            [15.0, -2.0, 0.5],  # also
            [WALL_X_M, 0.3, 1.0],  # on the wall: the rays end there
            [WALL_X_M - 0.1, 0.3, 1.0],  # 10 cm before it: closer than the returns' noise
            [30.0, 15.0, 0.0],  # on the street: the row below ends before it (a grazing ray passes over it)
            [14.0, 12.0, 0.05],  # 5 cm over the street, beside the wall
            [10.0, 0.3, 9.0],  # above the lidar's top row: no bracket
            [-10.0, 0.3, 1.0],  # in the air behind it: the rays either side meet the street 20 m out
            [-10.0, 0.3, -0.5],  # under the street: the rays end before it
        ]
    )
    expected = [True, True, False, False, False, False, False, True, False]
    assert sight.passed(places).tolist() == expected
    # one ray beyond is not enough: the street 30 m out lies between rows whose upper ray lands
    # beyond it, so a single-ray rule calls the street empty
    street = np.array([[30.0 * np.cos(a), 30.0 * np.sin(a), 0.0] for a in np.radians(np.arange(100, 260, 7.0))])
    assert not sight.passed(street).any()


@pytest.fixture(scope="module")
def moving_log(tmp_path_factory):
    """A 2 s synthetic TbV log (no cameras; nothing drives through a standing object), converted
    with the defaults: ``dynamic_flag`` from the lidar."""
    tmp = Path(tmp_path_factory.mktemp("motion"))
    config = SynthConfig(seconds=2.0, seed=302, tbv=True, keep_truth=True, camera_fps=0, clear_paths=True)
    truth = write_log(UPath(tmp / "src"), config)
    folder = tmp / "out" / truth.log_id
    convert_log(UPath(tmp / "src"), UPath(folder), truth.log_id, Argoverse2Options(split=None))
    return truth, open_sequence(folder, truth.log_id), folder


def _read_flags(loader, name: str = contract.DYNAMIC_FLAG) -> list[dict[int, np.ndarray]]:
    """Each sweep's ``dynamic_flag`` (or ``name``) per unit (0, 1: ``av2.LIDARS``), as 3DGRUT reads
    them (the point-cloud-source API)."""
    sources = [loader.get_point_clouds_source(unit) for unit in av2.LIDARS]
    return [{u: s.get_pc_generic_data(i, name) for u, s in enumerate(sources)} for i in range(sources[0].pcs_count)]


def _score(truth, flags: list[dict[int, np.ndarray]]) -> tuple[float, float, float]:
    """SA, DA and the share of the moving points that 3DGRUT's rule (drop ``dynamic_flag == 1``)
    leaves in its static cloud."""
    static_ok = static = moving_ok = moving = kept_moving = 0
    for k, sweep in enumerate(truth.sweeps):
        on_mover = truth.sweep_returns(k)["moving"]
        for u, flag in flags[k].items():
            truly = on_mover[sweep.unit == u]
            said = flag == 1
            static_ok, static = static_ok + (~said & ~truly).sum(), static + (~truly).sum()
            moving_ok, moving = moving_ok + (said & truly).sum(), moving + truly.sum()
            kept_moving += (truly[flag != 1]).sum()
    assert moving > 10_000 and static > 100_000
    return static_ok / static, moving_ok / moving, kept_moving / moving


#: SA and DA: issue 53's bounds (SA 0.9999, DA 0.9864 measured on this log). A flag flipped on every
#: point fails both.
SA_BOUND, DA_BOUND = 0.995, 0.95


def test_lidar_flags_against_the_generators_truth(moving_log):
    truth, loader, _ = moving_log
    sa, da, kept = _score(truth, _read_flags(loader))
    print(f"seed 302 through the converter: SA {sa:.4f}, DA {da:.4f}, kept {kept:.4f}")
    assert sa >= SA_BOUND and da >= DA_BOUND, (sa, da)
    assert kept <= 1 - DA_BOUND, kept  # 3DGRUT's static cloud keeps no more of the movers than DA misses
    flipped = [{u: (1 - f).astype(np.int8) for u, f in sweep.items()} for sweep in _read_flags(loader)]
    sa, da, _ = _score(truth, flipped)
    assert sa < SA_BOUND and da < DA_BOUND  # the planted control fails both


def _hidden(truth, k: int, picks: np.ndarray) -> np.ndarray:
    """Which returns ``picks`` (indices into sweep ``k``'s) no sweep the window tests them against
    (``motion_window.OFFSETS`` away) had a line of sight to, in truth: from where each of its units was
    (the middle of its sweep), at the time it looked that way (its return nearest in azimuth), the
    generator's scene ray-cast toward the place stops more than 0.3 m short of it, or the place lies
    outside the unit's rows (the elevations its returns span). bool [len(picks)]."""
    places = truth.sweep_returns(k)["xyz_m"][picks]
    seen = np.zeros(len(picks), bool)
    for j in (k + d for d in motion_window.OFFSETS if 0 <= k + d < len(truth.sweeps)):
        other, times_s = truth.sweep_returns(j), (truth.sweeps[j].time_ns - truth.t0_ns) * 1e-9
        for u in (0, 1):
            mine = other["unit"] == u
            origin = np.median(other["origin_m"][mine], axis=0)
            returns, to_place = other["xyz_m"][mine] - origin, places - origin
            distance = np.linalg.norm(to_place, axis=1)
            direction = to_place / distance[:, None]
            elevation = np.arcsin(returns[:, 2] / np.linalg.norm(returns, axis=1))
            azimuth = np.arctan2(returns[:, 1], returns[:, 0])
            order = np.argsort(azimuth)
            nearest = np.clip(
                np.searchsorted(azimuth[order], np.arctan2(direction[:, 1], direction[:, 0])), 0, len(order) - 1
            )
            range_m, _, _ = cast_rays(
                np.repeat(origin[None], len(picks), axis=0),
                direction,
                times_s[mine][order][nearest],
                truth.scene,
                200.0,
            )
            in_rows = (np.arcsin(direction[:, 2]) >= elevation.min()) & (np.arcsin(direction[:, 2]) <= elevation.max())
            seen |= in_rows & (range_m >= distance - 0.3)
    return ~seen


def _hidden_samples(truth, per_sweep: int = 4000) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per sweep, up to ``per_sweep`` of its returns on objects, which of them are hidden from every
    other sweep the window tests (:func:`_hidden`), and which are on movers."""
    rng, out = np.random.default_rng(0), []
    for k, sweep in enumerate(truth.sweeps):
        on_objects = np.flatnonzero(sweep.box_index >= 0)
        picks = rng.choice(on_objects, min(per_sweep, len(on_objects)), replace=False)
        out.append((picks, _hidden(truth, k, picks), truth.sweep_returns(k)["moving"][picks]))
    return out


def _unknown_figures(truth, flags, unknown, samples) -> tuple[float, float, int]:
    """The share of every point marked unknown; and of the hidden ``samples`` (:func:`_hidden_samples`),
    the share judged right (flag = truth) or marked unknown, and how many."""
    marked = points = hidden = right_or_unknown = 0
    for k, (sweep, (picks, out_of_sight, moving)) in enumerate(zip(truth.sweeps, samples, strict=True)):
        flag, said = np.zeros(len(sweep.unit), bool), np.zeros(len(sweep.unit), bool)
        for u in flags[k]:
            flag[sweep.unit == u], said[sweep.unit == u] = flags[k][u] == 1, unknown[k][u] == 1
        marked, points = marked + said.sum(), points + len(said)
        ok = said[picks] | (flag[picks] == moving)
        hidden, right_or_unknown = hidden + out_of_sight.sum(), right_or_unknown + (out_of_sight & ok).sum()
    return marked / points, right_or_unknown / max(hidden, 1), hidden


#: The unknown share of all points (0.43 % measured on this log), and of the returns hidden from
#: every other sweep the window tests, the share judged right or marked unknown (0.986 measured: an
#: object is judged by its parts other sweeps saw).
UNKNOWN_SHARE_BOUND, HIDDEN_RIGHT_BOUND = 0.02, 0.95


def test_unknown_marks_what_the_lidar_could_not_judge(moving_log):
    """``dynamic_flag_unknown`` against the generator's truth: few points (at most 2 %), never on a
    flagged one, and where the truth says no other sweep could see a place, the answer is right or
    marked unknown. Flipping the flags, or the field, fails the bounds."""
    truth, loader, _ = moving_log
    flags, unknown = _read_flags(loader), _read_flags(loader, contract.DYNAMIC_UNKNOWN)
    samples = _hidden_samples(truth)
    share, hidden_ok, hidden = _unknown_figures(truth, flags, unknown, samples)
    print(f"unknown: {share:.4f} of the points; {hidden} hidden returns sampled, {hidden_ok:.3f} right or unknown")
    assert hidden > 50 and share <= UNKNOWN_SHARE_BOUND and hidden_ok >= HIDDEN_RIGHT_BOUND, (share, hidden_ok)
    assert all(not np.any((f == 1) & (unknown[k][u] == 1)) for k, s in enumerate(flags) for u, f in s.items())
    flipped = [{u: (1 - f).astype(np.int8) for u, f in sweep.items()} for sweep in flags]
    assert _unknown_figures(truth, flipped, unknown, samples)[1] < HIDDEN_RIGHT_BOUND  # planted controls fail
    flipped = [{u: (1 - f).astype(np.int8) for u, f in sweep.items()} for sweep in unknown]
    assert _unknown_figures(truth, flags, flipped, samples)[0] > UNKNOWN_SHARE_BOUND


def test_lidar_flags_say_where_they_come_from(moving_log):
    _, loader, folder = moving_log
    for unit in av2.LIDARS:
        notes = component_meta(loader, LidarSensorComponent, unit)
        note = notes[contract.DYNAMIC_FLAG]
        assert note.startswith("written") and "lidar free space" in note, note
        assert notes[contract.DYNAMIC_UNKNOWN].startswith("written")
    sequence = json.loads(next(folder.glob("*.json")).read_text())["generic_meta_data"]
    source = sequence[contract.DYNAMIC_FLAG_SOURCE]
    assert source["source"] == "lidar free space" and source["lidar free space"]["parameters"]["sweep_offsets"]
    assert contract.DYNAMIC_UNKNOWN in source["lidar free space"]["not_known"]


def _in_annotation(box, t_s: float, xyz_city_m: np.ndarray) -> bool:
    """Whether a point (city frame, [3]) lies in ``box``'s annotation at ``t_s`` grown by the
    converter's 0.5 m margin."""
    T = box.T_annotated_city(t_s)
    local = (xyz_city_m - T[:3, 3]) @ T[:3, :3]
    return bool(np.all(np.abs(local) <= box.dims_m / 2 + BOX_MARGIN_M))


def test_both_keeps_every_annotated_mover_and_never_flags_a_standing_track(tmp_path):
    """``--dynamic-source both`` on a synthetic AV2 log, against ``annotations`` on the same log:
    every point the annotations flag stays flagged (every return on a track the converter calls
    dynamic among them), and no return on a standing track within its annotation's 0.5 m margin is
    flagged beyond what the annotations flag. (Returns further out are the annotation's error, which
    the converter cannot know: on this seed a parked car annotated 0.4-0.8 m off its true place, a
    pedestrian passing beside it, gets 80 flags from the lidar; docs/motion.md.) The camera-label
    jobs keep the annotated movers under ``lidar``."""
    config = SynthConfig(seconds=1.5, seed=303, keep_truth=True, camera_fps=0, clear_paths=True)
    truth = write_log(UPath(tmp_path / "src" / "val"), config)
    flags = {}
    for source in ("annotations", "both"):
        folder = tmp_path / source / truth.log_id
        convert_log(
            UPath(tmp_path / "src"), UPath(folder), truth.log_id, Argoverse2Options(split="val", dynamic_source=source)
        )
        loader = open_sequence(folder, truth.log_id)
        flags[source] = _read_flags(loader)
        meta = json.loads(next(folder.glob("*.json")).read_text())["generic_meta_data"][contract.DYNAMIC_FLAG_SOURCE]
        assert meta["source"] == {"annotations": "annotations", "both": "annotations and lidar free space"}[source]
    dynamic = set(component_meta(loader, CuboidsComponent, "default")[contract.DYNAMIC_TRACKS])
    annotated = np.array([b.annotated for b in truth.scene.boxes])
    on_dynamic = np.array([b.track_uuid in dynamic for b in truth.scene.boxes])
    movers = mover_flagged = standing = standing_added = beyond_margin = kept = annotated_flags = 0
    for k, sweep in enumerate(truth.sweeps):
        xyz_city_m = truth.sweep_returns(k)["xyz_m"]
        for u in (0, 1):
            rows = np.flatnonzero(sweep.unit == u)
            box = sweep.box_index[rows]
            hit = box >= 0
            mover = hit & on_dynamic[np.maximum(box, 0)]
            still = hit & annotated[np.maximum(box, 0)] & ~mover
            both, by_annotations = flags["both"][k][u] == 1, flags["annotations"][k][u] == 1
            movers, mover_flagged = movers + mover.sum(), mover_flagged + (mover & both).sum()
            added = np.flatnonzero(still & both & ~by_annotations)
            t_s = (sweep.time_ns[rows[added]] - truth.t0_ns) * 1e-9
            boxes = truth.scene.boxes
            near = [_in_annotation(boxes[box[i]], t, xyz_city_m[rows[i]]) for i, t in zip(added, t_s, strict=True)]
            standing, standing_added = standing + still.sum(), standing_added + sum(near)
            beyond_margin += len(added) - sum(near)
            kept, annotated_flags = kept + (by_annotations & both).sum(), annotated_flags + by_annotations.sum()
    assert movers > 1000 and mover_flagged == movers, (mover_flagged, movers)
    assert kept == annotated_flags > 0
    assert standing > 1000 and standing_added == 0, (standing_added, beyond_margin, standing)
    # the camera-label jobs' points keep the annotated movers whatever --dynamic-source says (under
    # `lidar` they would otherwise take every point as static: stale movers in the depth labels)
    options = Argoverse2Options(split="val", dynamic_source="lidar", ego_masks="none")
    plan = plan_log(UPath(tmp_path / "src"), truth.log_id, options)
    with Reader(plan.inputs.reading) as reader:
        for k, (_, _, data) in enumerate(label_sweeps(plan, reader, None)):
            annotated_flags = np.concatenate([flags["annotations"][k][u] for u in (0, 1)]) == 1
            assert np.array_equal(data.dynamic, annotated_flags)


def test_no_point_of_a_standing_track_is_flagged_on_the_real_sample(av2_sample_root, tmp_path):
    """The real sample's 2 sweeps with ``--dynamic-source lidar``: no point inside a standing
    (static) track's box is flagged. What two sweeps 0.1 s apart allow of the moving tracks is
    reported (docs/motion.md), not bounded."""
    out = tmp_path / AV2_SAMPLE_LOG
    options = Argoverse2Options(split="val", dynamic_source="lidar", camera_ids=())
    convert_log(UPath(av2_sample_root), UPath(out), AV2_SAMPLE_LOG, options)
    loader = open_sequence(out, AV2_SAMPLE_LOG)
    observations = list(loader.get_cuboid_track_observations())
    dynamic = set(component_meta(loader, CuboidsComponent, "default")[contract.DYNAMIC_TRACKS])
    standing = inside = moving = found = 0
    for unit in av2.LIDARS:
        source = loader.get_point_clouds_source(unit)
        lidar = loader.get_lidar_sensor(unit)
        for i in range(source.pcs_count):
            flag = source.get_pc_generic_data(i, "dynamic_flag") == 1
            start_us = int(lidar.frames_timestamps_us[i, 0])
            xyz_world, _ = world_points(loader, unit, i)  # NCore's motion compensation, per-point times
            T_rig_world = loader.pose_graph.evaluate_poses("rig", "world", np.array([start_us], dtype=np.uint64))[0]
            xyz_rig = ((xyz_world - T_rig_world[:3, 3]) @ T_rig_world[:3, :3].astype(np.float64)).astype(np.float32)
            for box in (b for b in observations if b.timestamp_us == start_us):
                row = np.array([[*box.bbox3.centroid, *box.bbox3.dim, *box.bbox3.rot]], dtype=np.float32)
                within = is_within_3d_bboxes(xyz_rig, row).ravel()
                if box.track_id in dynamic:
                    moving, found = moving + within.sum(), found + (within & flag).sum()
                else:
                    standing, inside = standing + within.sum(), inside + (within & flag).sum()
    print(f"real sample, 2 sweeps: {found} of {moving} points of the moving tracks flagged")
    assert standing > 5000 and inside == 0, (inside, standing)
