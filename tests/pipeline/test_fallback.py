"""The FPFH second opinion below the gate (pipeline/fallback.py)."""

from __future__ import annotations

import numpy as np
import pytest

from byoc_cli.pipeline.registrar import Registrar
from tests._rings import room_scan
from tests.pipeline._clouds import cube, moved


def test_the_fallback_keeps_the_more_confident_features_in_the_input_units():
    src_mm = cube(1) * 1000
    tgt, T = moved(cube(1))
    tgt_mm = tgt * 1000
    mm = {"seed": 1, "scale": 0.001}  # a box of 3 m, not a room ten times the trained size
    plain = Registrar(fallback=None).register(src_mm, tgt_mm, **mm)
    assert plain.fallback is None
    never = Registrar(fallback="fpfh", fallback_below=0.0).register(src_mm, tgt_mm, **mm)
    assert never.fallback is None and np.array_equal(never.T_tgt_src, plain.T_tgt_src)
    both = Registrar(fallback="fpfh", fallback_below=1.0).register(src_mm, tgt_mm, **mm)
    note = both.fallback
    assert note["features"] == "fpfh" and note["learned_confidence"] == plain.confidence
    assert note["confidence"] is not None and note["seconds"] > 0
    assert note["voxel_choice"]["voxel_size"] > 0  # FPFH's own choice, said apart
    assert both.confidence == max(plain.confidence, note["confidence"])
    assert both.features == ("fpfh" if note["used"] else "byoc")
    assert note["used"] == (note["confidence"] > plain.confidence)
    assert both.timings["fallback"] == note["seconds"] and "fallback" not in plain.timings
    assert np.abs(both.T_tgt_src[:3, 3] - 1000 * T[:3, 3]).max() < 50  # mm, either way
    with pytest.raises(ValueError, match="fallback"):
        Registrar("fpfh", fallback="fpfh")


def test_the_fallback_does_each_clouds_work_once_and_gives_what_fpfh_gives(monkeypatch):
    import byoc_cli.pipeline.scale as scale

    a, b = cube(1), moved(cube(1))[0]
    registrar = Registrar(fallback="fpfh", fallback_below=1.0)  # always runs
    measured = []
    monkeypatch.setattr(
        scale,
        "measure",
        lambda p, label="cloud", lines=True, f=scale.measure, **kw: (
            measured.append(label) or f(p, label, lines, **kw)
        ),
    )
    choice = registrar.choose_voxel(a, b)  # the pair's voxel, as register-batch reads it
    assert len(measured) == 2 and choice.keep_of(0) == choice.keep_of(1) == 1.0
    fa, fb = (
        registrar.extract_points(p, 1.0, "cloud", choice.voxel_size, choice.refine_voxel)
        for p in (a, b)
    )
    extracted = []
    real = Registrar.extract_points
    monkeypatch.setattr(
        Registrar,
        "extract_points",
        lambda self, *args, **kw: extracted.append(self.features) or real(self, *args, **kw),
    )
    pairs = [(fa, fb), (fb, fa), (fa, fb)]
    got = [registrar.match(s, t, seed=2) for s, t in pairs]
    assert [r.fallback is not None for r in got] == [True] * 3
    assert len(measured) == 4  # each cloud once more, by the fallback, then kept
    assert extracted.count("fpfh") == 2  # each cloud's FPFH features once
    assert got[2].T_tgt_src.tobytes() == got[0].T_tgt_src.tobytes()
    fresh = Registrar("fpfh")
    for (s, t), result in zip(pairs[:2], got, strict=False):
        alone = fresh.register(s.cloud, t.cloud, scale=1.0, refine="multiscale", seed=2)
        assert result.fallback["confidence"] == alone.confidence
        if result.fallback["used"]:
            assert result.T_tgt_src.tobytes() == alone.T_tgt_src.tobytes()


def test_coarser_fpfh_features_keep_the_refinements_voxel():
    a, b = cube(1), moved(cube(1))[0]
    made = Registrar()
    scales = [made.cloud_scale(a, "source"), made.cloud_scale(b, "target")]
    plain = made.fpfh_registration((a, b), scales, 3)
    coarse = made.fpfh_registration((a, b), scales, 3, coarser=1.4)
    assert coarse.voxel_size == pytest.approx(1.4 * plain.voxel_size)
    assert coarse.voxel_choice["voxel_size"] == pytest.approx(1.4 * plain.voxel_size)
    same = coarse.voxel_choice["refine_voxel_size"] == plain.voxel_choice["refine_voxel_size"]
    assert same and coarse.num_points_src < plain.num_points_src  # fewer kept points
    again = made.fpfh_registration((a, b), scales, 3)  # the plain features, as before
    assert again.T_tgt_src.tobytes() == plain.T_tgt_src.tobytes()


def test_fpfh_sizes_a_laser_scanned_room_by_the_room_and_the_learned_features_do_not():
    """A scan from inside a room: its points crowd around the scanner. The learned features'
    auto voxel reads its raw radius; FPFH's (the fallback's registrar, --features fpfh) the
    radius of the room thinned evenly, larger."""
    room = room_scan(0.5)
    learned = Registrar(fallback="fpfh")
    scale = learned.cloud_scale(room, "room")
    assert scale.even_radius > 1.3 * scale.radius
    fpfh = Registrar("fpfh")
    assert learned.voxel_for(scale, scale).voxel_size == pytest.approx(
        learned.voxel_size * scale.radius
    )
    assert fpfh.voxel_for(scale, scale).voxel_size == pytest.approx(
        fpfh.voxel_size * scale.even_radius
    )


def test_on_panoramas_larger_than_the_trained_range_fpfh_checks_its_result_against_turns():
    from byoc_cli.pipeline.fallback import LARGE_SCANS, Fallback, changes_for
    from byoc_cli.pipeline.scale import CloudScale

    room = CloudScale(200_000, 0.005, 1.4, even_radius=2.4)  # crowded near its scanner
    fragment = CloudScale(200_000, 0.005, 1.2, even_radius=1.25)
    hall = CloudScale(400_000, 0.01, 12.0, even_radius=15.0)  # a panorama of a large hall
    street = CloudScale(40_000, 0.05, 12.0)  # LiDAR: no panorama, no even radius
    small = CloudScale(20_000, 0.0005, 0.05, even_radius=0.06)
    assert changes_for([room, room]) == changes_for([hall, hall]) == LARGE_SCANS
    assert changes_for([fragment, fragment]) == changes_for([small, small]) == ()
    assert changes_for([street, street]) == ()
    assert Fallback("auto").registrar(LARGE_SCANS).recipe.matching.turns
    assert not Fallback("auto").registrar().recipe.matching.turns


def test_the_learned_features_results_on_laser_scanned_rooms_are_checked_against_turns():
    """large_panoramas: a room's scans (panoramas larger than the trained range) mark the
    pair for the structure check of rooms; a Kinect-sized cloud, a pair without clouds or a
    hand-set voxel do not."""
    from types import SimpleNamespace

    from byoc_cli.pipeline.fallback import large_panoramas

    room = SimpleNamespace(cloud=room_scan(1.0))
    made = Registrar()
    assert large_panoramas(made, room, room)
    small = SimpleNamespace(cloud=room_scan(1.0) / 10.0)  # a box of 0.4 m: the trained range
    assert not large_panoramas(made, small, small)
    assert not large_panoramas(made, room, SimpleNamespace(cloud=None))
    assert not large_panoramas(Registrar(voxel_size=0.025), room, room)


def _scale(radius: float, even_radius: float | None = None):
    from byoc_cli.pipeline.scale import CloudScale

    return CloudScale(50_000, radius / 200, radius, even_radius=even_radius)


@pytest.mark.parametrize(
    ("radii", "objects"),
    [
        ((0.06, 0.05), True),  # a 10 cm object in metres: below the trained size
        ((1.0, 1.2), False),  # depth frames and fragments: within it
        ((0.06, 1.0), False),  # the pair's size (the larger) is within it
        ((60.0, 55.0), False),  # millimetres, or a georeferenced LiDAR scan: above it
    ],
)
def test_small_objects_are_clouds_below_the_trained_size(radii, objects):
    from byoc_cli.pipeline.fallback import small_objects

    assert small_objects([_scale(r) for r in radii]) == objects
    assert small_objects([_scale(r, r * 1.3) for r in radii]) == objects  # panoramas alike


@pytest.mark.parametrize(("origin", "objects"), [(9.0, True), (2.5, False), (0.1, False)])
def test_an_object_in_millimetres_seen_from_outside_is_small_too(origin, objects):
    """Radii of 55 and 60 units: a 10 cm object in millimetres, or a 110 m scene. Seen from 9
    radii away (a scanner looking at an object) it is an object; from 2.5 (a depth frame, a
    fragment) or 0.1 (a LiDAR scan, a terrestrial scan around its scanner) it is not."""
    from byoc_cli.pipeline.fallback import small_objects

    scales = [_scale(r)._replace(origin_radii=origin, spacing_spread=1.6) for r in (60.0, 55.0)]
    assert small_objects(scales) == objects


class _Fpfh:
    """The FPFH registrations a :class:`Fallback` stand-in gives its repeats: ``T`` in turn."""

    def __init__(self, repeats):
        self.repeats, self.calls = list(repeats), []

    def __call__(self, clouds, scales, seed, changes=()):
        self.calls.append((seed, changes))
        return _fpfh_registration(0.3, self.repeats.pop(0))


def _fpfh_registration(confidence: float, T: np.ndarray, rmse: float = 0.2):
    from byoc_cli.pipeline.results import Registration

    return Registration(
        T, confidence, False, 10, 2000, 0.005, 0.05, 100, 100, 0.1, 0.01, "fpfh",
        "ransac", "multiscale", 1000, 100, 0, None, {"fit": 0.1}, cues={"rmse": rmse},
    )  # fmt: skip


def _features(points: np.ndarray):
    from types import SimpleNamespace

    return SimpleNamespace(cloud=points, scale=1.0)


@pytest.mark.parametrize(("turned", "agree"), [(0.0, True), (90.0, False)])
def test_a_fallback_result_below_the_gate_is_repeated_and_passes_when_both_agree(turned, agree):
    from byoc_cli.geometry.transforms import axis_angle_matrix
    from byoc_cli.pipeline.fallback import Fallback
    from byoc_cli.pipeline.feature_choice import REPEATS, REPRODUCED_CONFIDENCE

    T = np.eye(4)
    T[0, 3] = 0.01
    other = T.copy()
    other[:3, :3] = axis_angle_matrix(np.array([0.0, 0.0, np.radians(turned)]))
    fallback = Fallback("auto")
    fallback.register = _Fpfh([T, other])
    src = _features(cube(1) * 0.05)
    got = fallback._repeated(_fpfh_registration(0.05, T), 0.45, src, src, (7, (), None))
    assert got.reproduced["agree"] == agree and got.reproduced["model_confidence"] == 0.05
    assert got.confidence == (REPRODUCED_CONFIDENCE if agree else 0.05)
    assert fallback.register.calls == [(8, ()), (7, REPEATS[1][2])]


@pytest.mark.parametrize(("confidence", "rmse"), [(0.5, 0.2), (0.05, 0.3)])
def test_no_repeats_above_the_gate_or_with_a_large_residual(confidence, rmse):
    from byoc_cli.pipeline.fallback import Fallback

    fallback = Fallback("auto")
    fallback.register = _Fpfh([])
    first = _fpfh_registration(confidence, np.eye(4), rmse)
    src = _features(cube(1))
    got = fallback._repeated(first, 0.45, src, src, (0, (), None))
    assert got is first and fallback.register.calls == []
