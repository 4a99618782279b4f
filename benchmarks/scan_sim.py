"""Simulated scans with ground truth: spinning LiDAR of a street, laser scans of an object.

Development data that looks like the LiDAR and laser scans users bring, made deterministically
from a seed (``np.random.default_rng``; no global RNG):

* **street**: a street scene (buildings along both sides, some with recesses, kerbs, poles and
  street lamps, parked cars, trees, the ground) as an Open3D triangle mesh, about 80 m long,
  ray-cast from a spinning LiDAR 1.8 m above the road (16-128 rings over -25..+15 deg, an
  azimuth resolution picked for the asked number of points, 100 m range, 1.5 cm range noise).
  Points are in the sensor's frame, as a LiDAR writes them: the ring pattern is fixed to the
  sensor and the density falls with range. Scan B's sensor is 4 m ahead and turned 12 deg.
* **object**: a triangle mesh fused (TSDF, Open3D ``VoxelBlockGrid``) from a real RGB-D
  sequence (``rgbd/realsense_tabletop`` of the shared data: an open box with objects in it on
  a table), the table cut off, scaled to 20 cm, ray-cast by a dense pinhole laser scanner
  (0.5 mm spacing on the object, 0.1 mm range noise) from two viewpoints 45 deg apart on the
  arc the real camera covered. Points are in the scanner's frame (z forward, y down).
* **room**: furnished rooms (walls with door and window openings, an optional partition wall,
  tables, shelves, chairs, boxes, cylinders; some laid out symmetrically) scanned from two
  positions 1-4 m apart by a terrestrial laser scanner (panoramic, -60..+90 deg, 3 mm range
  noise, 100k-1M points) or a rotating 2D laser (1-3 cm noise, scan lines a few cm apart),
  each scan in its scanner's frame at a random heading; ``DIR/pairs.txt`` lists them for
  ``benchmarks/objects.py run`` (``_scan_sim_room.py``, ``_scan_sim_room_scan.py``).
* **geo / hostile** variants of a pair: offsets of 1e3 .. 1e7 m (UTM-like), a stray point at
  1e6 m or 1e30 m, duplicated points, clouds scaled by 1e30 and 1e300, float32 coordinates at
  a 1e9 m offset.

Every pair is ``(src (N, 3) float64, tgt (M, 3) float64, T_gt (4, 4) float64)`` with
``T_gt`` mapping the source's frame into the target's (``x_tgt = R x_src + t``).

Usage::

    python benchmarks/scan_sim.py --out DIR [--sets street object room geo hostile]
        [--sizes 42000 1100000] [--cache DIR] [--seed 0] [--preview]
        [--rooms r0-tls-1.5m ...] [--room-points 20000]

writes each pair as ``DIR/<name>/{source.ply,target.ply,T_gt.txt,info.json}`` (float64 PLY
where float32 would lose more than a millionth of the cloud's size, else float32).

This file is the command; the parts are its siblings: `_scan_sim_geometry.py` (transforms, ray
casting), `_scan_sim_street.py`, `_scan_sim_object.py`, `_scan_sim_variants.py` (geo, hostile)
and `_scan_sim_write.py` (PLY, ``info.json``, top view). Laser scans of procedural free-form
objects (no table: deformed spheres, superquadrics, tori, unions of blobs) are
`_scan_sim_shapes.py`'s, made by ``benchmarks/objects.py make``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from _scan_sim_geometry import Pair, apply, raycasting_scene, rigid, rotation_xyz, scan
from _scan_sim_object import DATA, OBJECT_SEQUENCE, OBJECT_VOXEL_FRACTION, ROOT, object_pair
from _scan_sim_room_scan import ROOM_PAIRS, room_pair
from _scan_sim_street import (
    STREET_VOXEL,
    lidar_directions,
    made_street,
    simulate_street,
    street_pair,
    street_settings,
)
from _scan_sim_variants import Variant, geo_variants, georeferenced, hostile_variants, scaled
from _scan_sim_write import size_name, top_view, write_pair

__all__ = [  # what the tests and scaling.py use, and the command
    "STREET_VOXEL",
    "apply",
    "georeferenced",
    "lidar_directions",
    "made_street",
    "main",
    "object_pair",
    "raycasting_scene",
    "rigid",
    "room_pair",
    "rotation_xyz",
    "scaled",
    "scan",
    "simulate_street",
    "size_name",
    "street_pair",
    "street_settings",
    "write_pair",
]

SETS = ("street", "object", "room", "geo", "hostile")
ROOM_NAMES = [name for name, *_ in ROOM_PAIRS]


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder of the pairs")
    parser.add_argument(
        "--sets",
        nargs="+",
        default=list(SETS),
        metavar="SET",
        help=f"of {', '.join(SETS)} (default: all)",
    )
    parser.add_argument(
        "--sizes",
        nargs="+",
        type=int,
        default=[42000, 1100000],
        help="points per scan of the street pairs",
    )
    parser.add_argument(
        "--variants-of",
        nargs="+",
        default=["street"],
        choices=("street", "object"),
        help="pairs the geo and hostile variants are made of: the street at the "
        "first --sizes, the object (default: street)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shift", type=float, default=4.0, help="street: metres between scans")
    parser.add_argument("--yaw", type=float, default=12.0, help="street: degrees between scans")
    parser.add_argument(
        "--angles",
        nargs="+",
        type=float,
        default=[45.0],
        help="object: degrees between the two viewpoints",
    )
    parser.add_argument(
        "--rooms",
        nargs="+",
        default=ROOM_NAMES,
        choices=ROOM_NAMES,
        metavar="NAME",
        help="room: the pairs (default: all of _scan_sim_room_scan.ROOM_PAIRS)",
    )
    parser.add_argument(
        "--room-points", type=int, help="room: points per scan of every pair (default: its own)"
    )
    parser.add_argument("--data", type=Path, default=DATA, help="the shared data folder")
    parser.add_argument("--cache", type=Path, help="folder for the fused object mesh")
    parser.add_argument(
        "--preview", action="store_true", help="also a top-view PNG of each street pair's source"
    )
    args = parser.parse_args(argv)
    unknown = sorted(set(args.sets) - set(SETS))
    if unknown:
        parser.error(f"--sets {unknown[0]!r}: not one of {', '.join(SETS)}")
    if args.cache is not None and args.cache.resolve().is_relative_to(ROOT):
        parser.error(f"--cache {args.cache}: inside the repository; give a folder outside it")
    if "object" in args.sets or "object" in args.variants_of:
        if not (args.data / OBJECT_SEQUENCE).is_dir():
            parser.error(f"--data {args.data}: no {OBJECT_SEQUENCE} (the object's RGB-D video)")
    if not set(args.sets) & {"street", "geo", "hostile"} and "street" in args.variants_of:
        args.variants_of = [v for v in args.variants_of if v != "street"]
    return args


def _bases(args: argparse.Namespace) -> dict[str, tuple[Pair, dict]]:
    """The pairs of the sets asked: street pairs by size, object pairs by angle, with info."""
    pairs: dict[str, tuple[Pair, dict]] = {}
    want_street = "street" in args.sets or "street" in args.variants_of
    sizes = args.sizes if "street" in args.sets else args.sizes[:1]
    for n in sizes if want_street else []:
        pairs[f"street-{size_name(n)}"] = made_street(n, args.seed, args.shift, args.yaw)
    want_object = "object" in args.sets or "object" in args.variants_of
    for angle in args.angles if want_object else []:
        sequence = args.data / OBJECT_SEQUENCE
        pair = object_pair(angle, seed=args.seed, sequence=sequence, cache=args.cache)
        info = {"kind": "object", "angle_deg": angle, "seed": args.seed, "scene_size_m": 0.2,
                "voxel": 0.2 * OBJECT_VOXEL_FRACTION, "sequence": OBJECT_SEQUENCE}  # fmt: skip
        pairs[f"object-{angle:g}deg"] = (pair, info)
    return pairs


def _rooms(args: argparse.Namespace) -> None:
    """The room pairs asked, and ``pairs.txt`` listing them (``source target out/<name>.txt``)."""
    lines = []
    for name, seed, layout, sensor, points, distance, cross in ROOM_PAIRS:
        if name not in args.rooms:
            continue
        points = args.room_points or points
        pair, info = room_pair(seed, layout, sensor, points, distance, cross, args.seed)
        written = write_pair(args.out / name, pair, info)
        lines.append(f"{name}/source.ply {name}/target.ply out/{name}.txt")
        print(f"{name}: {written['points_src']} + {written['points_tgt']} points, "
              f"overlap {info['overlap']:.2f}", file=sys.stderr)  # fmt: skip
    (args.out / "pairs.txt").write_text("\n".join(lines) + "\n")
    (args.out / "out").mkdir(exist_ok=True)


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    if "room" in args.sets:
        _rooms(args)
    bases = _bases(args)
    variants: dict[str, Variant] = {}
    if "geo" in args.sets:
        variants.update(geo_variants())
    if "hostile" in args.sets:
        variants.update(hostile_variants())
    for name, (pair, info) in bases.items():
        if info["kind"] in args.sets:
            written = write_pair(args.out / name, pair, info)
            print(
                f"{name}: {written['points_src']} + {written['points_tgt']} points, "
                f"{written['ply_dtype'][0]}",
                file=sys.stderr,
            )
            if args.preview and info["kind"] == "street":
                top_view(pair[0], args.out / name / "top.png", name)
        first = next(k for k, (_, i) in bases.items() if i["kind"] == info["kind"])
        if info["kind"] not in args.variants_of or name != first:
            continue
        for suffix, variant in variants.items():
            new_info = {
                **info,
                "variant": suffix,
                "of": name,
                "voxel": info["voxel"] * variant.voxel_factor,
            }
            written = write_pair(
                args.out / f"{name}-{suffix}", variant.make(*pair), new_info, variant.dtype
            )
            print(
                f"{name}-{suffix}: {written['points_src']} + {written['points_tgt']} points, "
                f"{written['ply_dtype'][0]}",
                file=sys.stderr,
            )


if __name__ == "__main__":
    main()
