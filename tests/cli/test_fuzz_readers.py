"""Fuzzing the readers through the commands that use them (hypothesis): PLY, PCD, NPY,
depth PNG, intrinsics, gt.log and weights files, mutated byte by byte or built with odd
values. Every run must end with exit 0 and a valid result, or exit 1 and one error line;
never a traceback or a raw warning, and never a changed file it did not create.

A few hundred cases per reader in CI (fixed seed); ``pytest --slow`` runs ten times as many
(random seeds).
"""

from __future__ import annotations

import functools
import io
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from byoc_cli.cli.main import cli
from byoc_cli.io import read_transform, write_ply
from tests._fuzzing import check_run, fuzz_settings, mutated, snapshot

RNG = np.random.default_rng(0)
BOX = RNG.uniform(-1, 1, size=(40, 3)) * np.array([1.5, 1.0, 0.8])


def _ply_ascii() -> bytes:
    head = "ply\nformat ascii 1.0\nelement vertex 40\nproperty float x\nproperty float y\n"
    head += "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    rows = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in BOX)
    return (head + rows + "3 0 1 2\n").encode()


def _ply_binary() -> bytes:
    with tempfile.TemporaryDirectory() as folder:
        write_ply(Path(folder) / "b.ply", BOX)
        return (Path(folder) / "b.ply").read_bytes()


def _las(suffix: str) -> bytes:
    """BOX as a LAS 1.4 (point format 6) or LAZ file, offsets and 0.1 mm scales."""
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = np.full(3, 1e-4), np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = BOX.T
    with tempfile.TemporaryDirectory() as folder:
        las.write(str(Path(folder) / f"a{suffix}"))
        return (Path(folder) / f"a{suffix}").read_bytes()


def _pcd_ascii() -> bytes:
    head = "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
    head += "WIDTH 40\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 40\nDATA ascii\n"
    return (head + "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in BOX)).encode()


def _pcd_binary() -> bytes:
    head = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
    head += "WIDTH 40\nHEIGHT 1\nPOINTS 40\nDATA binary\n"
    return head.encode() + BOX.astype("<f4").tobytes()


def _npy() -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, BOX)
    return buffer.getvalue()


def _png(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


DEPTH = np.full((12, 16), 1500, dtype=np.uint16)
DEPTH[::3, ::2] = 900
K_TEXT = "20 0 8\n0 20 6\n0 0 1\n"
K_JSON = json.dumps({"width": 16, "height": 12, "intrinsic_matrix": [20, 0, 0, 0, 20, 0, 8, 6, 1]})
GT_LOG = "0 1 2\n1 0 0 0.01\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"


class Folder:
    """A fresh folder with the good partner files; ``run`` checks one fuzzed run."""

    def __init__(self) -> None:
        self._tmp = tempfile.TemporaryDirectory()
        self.path = Path(self._tmp.name)
        write_ply(self.path / "good.ply", BOX + 0.01)
        (self.path / "depth.png").write_bytes(_png(DEPTH))
        (self.path / "K.txt").write_text(K_TEXT)

    def __enter__(self) -> Folder:
        return self

    def __exit__(self, *exc) -> None:
        self._tmp.cleanup()

    def write(self, name: str, data: bytes) -> Path:
        path = self.path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        return path

    def run(self, args: list, outputs: tuple[str, ...] = ()) -> bool:
        before = snapshot(self.path)
        result = CliRunner().invoke(cli, [str(a) for a in args])
        return check_run(result, before, snapshot(self.path), outputs)

    def benchmark_fragments(self) -> None:
        """Two fragments of a one-scene 3DMatch-layout benchmark under ``bench/``."""
        (self.path / "bench" / "kitchen").mkdir(parents=True, exist_ok=True)
        for k in range(2):
            write_ply(self.path / "bench" / "kitchen" / f"cloud_bin_{k}.ply", BOX + 0.01 * k)

    def register(self, source: Path, target: Path | None = None, *extra) -> None:
        out = self.path / "T.txt"
        args = ["register", source, target or self.path / "good.ply", "--features", "fpfh"]
        args += ["--min-confidence", "0"]  # the readers are fuzzed, not the gate (exit 3)
        if self.run([*args, "--voxel-size", "0.2", *extra, "-o", out], ("T.txt",)):
            T = read_transform(out)  # a valid rigid transform
            assert T.shape == (4, 4)


@pytest.mark.parametrize(
    ("name", "base"),
    [("a.ply", _ply_ascii()), ("b.ply", _ply_binary())],
    ids=["ascii", "binary"],
)
@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_ply(name, base, data):
    with Folder() as folder:
        folder.register(folder.write(name, data.draw(mutated(base))))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
@fuzz_settings(150)
@given(data=st.data())
def test_fuzz_las(suffix, data):
    # a corrupt count in a LAS header or a LAZ chunk table once made laspy loop for hours or
    # lazrs abort the process on an allocation of tens of GB
    with Folder() as folder:
        folder.register(folder.write(f"a{suffix}", data.draw(mutated(_las(suffix), 1200))))


@pytest.mark.parametrize("base", [_pcd_ascii(), _pcd_binary()], ids=["ascii", "binary"])
@fuzz_settings(150)
@given(data=st.data())
def test_fuzz_pcd(base, data):
    with Folder() as folder:
        folder.register(folder.write("c.pcd", data.draw(mutated(base))))


ODD_DTYPES = st.sampled_from(["<f8", ">f4", "<i2", "u1", "?", "<c16", "O", "<U3", "V12"])


@st.composite
def odd_npy(draw) -> bytes:
    """A valid NPY container of an odd array: shapes, dtypes (object ones need pickle)."""
    shape = draw(st.lists(st.integers(0, 5), min_size=0, max_size=3))
    dtype = np.dtype(draw(ODD_DTYPES))
    array = np.zeros(shape, dtype=dtype)
    if dtype.kind == "f" and array.size:
        array.flat[draw(st.integers(0, array.size - 1))] = draw(st.floats(allow_nan=True, width=32))
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


@fuzz_settings(300)
@given(data=st.data())
def test_fuzz_npy(data):
    blob = data.draw(mutated(_npy(), header_bytes=128) | odd_npy())
    with Folder() as folder:
        folder.register(folder.write("n.npy", blob))


@st.composite
def odd_image(draw) -> bytes:
    """A valid PNG of an odd size or pixel format."""
    height, width = draw(st.integers(1, 20)), draw(st.integers(1, 20))
    dtype = draw(st.sampled_from([np.uint16, np.uint8]))
    values = draw(st.integers(0, 65535 if dtype is np.uint16 else 255))
    array = np.full((height, width), values, dtype=dtype)
    if draw(st.booleans()):
        array = np.stack([array.astype(np.uint8)] * 3, axis=-1)
    return _png(array)


@fuzz_settings(300)
@given(data=st.data())
def test_fuzz_depth_png(data):
    blob = data.draw(mutated(_png(DEPTH), header_bytes=64) | odd_image())
    with Folder() as folder:
        depth = folder.write("d.png", blob)
        folder.register(depth, folder.path / "depth.png", "--intrinsics", folder.path / "K.txt")


@pytest.mark.parametrize(("name", "base"), [("K.json", K_JSON), ("K2.txt", K_TEXT)])
@fuzz_settings(200)
@given(data=st.data())
def test_fuzz_intrinsics(name, base, data):
    with Folder() as folder:
        intrinsics = folder.write(name, data.draw(mutated(base.encode())))
        depth = folder.path / "depth.png"
        folder.register(depth, depth, "--intrinsics", intrinsics)


@fuzz_settings(300)
@given(data=st.data())
def test_fuzz_gt_log(data):
    with Folder() as folder:
        folder.benchmark_fragments()
        folder.write("bench/kitchen-evaluation/gt.log", data.draw(mutated(GT_LOG.encode())))
        report = folder.path / "r.json"
        args = ["eval-fmr", folder.path / "bench", "--method", "identity", "--quiet"]
        if folder.run([*args, "--json", report], ("r.json",)):
            assert json.loads(report.read_text())["num_pairs"] >= 1


def _weights_blob(meta: dict, tensors: dict) -> bytes:
    from safetensors.torch import save

    return save(tensors, metadata={"byoc": json.dumps(meta)})


@functools.cache
def _base_weights_json() -> str:
    import torch

    from byoc_cli.pipeline.weights import init_weights, tensors_sha256

    _, meta = init_weights("compact", 0)
    meta["tensors_sha256"] = tensors_sha256({"w": torch.zeros(2)})
    return json.dumps(meta)


def _base_weights() -> tuple[dict, dict]:
    """The metadata of a real compact encoder, with a two-number tensor payload (writing
    and hashing a 26 MB file per case would make the fuzz test slow)."""
    import torch

    return json.loads(_base_weights_json()), {"w": torch.zeros(2)}


JSON_VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**12), 10**12)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=6,
)


@st.composite
def odd_weights(draw) -> bytes:
    """Real metadata with one value (at any depth) replaced, framing kept valid."""
    meta, tensors = _base_weights()
    target = meta
    key = draw(st.sampled_from(sorted(target)))
    while isinstance(target[key], dict) and target[key] and draw(st.booleans()):
        target = target[key]
        key = draw(st.sampled_from(sorted(target)))
    if draw(st.integers(0, 9)) == 0:
        del target[key]
    else:
        target[key] = draw(JSON_VALUES)
    return _weights_blob(meta, tensors)


@fuzz_settings(400)
@given(data=st.data())
def test_fuzz_weights(data):
    base = _weights_blob(*_base_weights())
    blob = data.draw(odd_weights() | mutated(base, header_bytes=len(base)))
    with Folder() as folder:
        path = folder.write("w.safetensors", blob)
        before = snapshot(folder.path)
        result = CliRunner().invoke(cli, ["weights", "info", str(path)])
        check_run(result, before, snapshot(folder.path))
        assert result.exit_code == 1  # the payload never matches the architecture
        assert str(path) in result.stderr


def test_the_weights_base_fails_only_at_the_tensors():
    """The fuzz base gets past every metadata check (so mutations explore them all)."""
    with Folder() as folder:
        path = folder.write("w.safetensors", _weights_blob(*_base_weights()))
        result = CliRunner().invoke(cli, ["weights", "info", str(path)])
        assert result.exit_code == 1 and "do not match architecture" in result.stderr


def test_the_bases_are_valid():
    """Unmutated, every base file gives exit 0 (the fuzz starts from valid inputs)."""
    with Folder() as folder:
        for name, base in [
            ("a.ply", _ply_ascii()),
            ("b.ply", _ply_binary()),
            ("c.pcd", _pcd_ascii()),
            ("d.pcd", _pcd_binary()),
            ("n.npy", _npy()),
        ]:
            out = folder.path / f"{name}.T.txt"
            source = folder.write(name, base)
            args = ["register", source, folder.path / "good.ply", "--features", "fpfh"]
            args += ["--min-confidence", "0"]
            result = CliRunner().invoke(
                cli, [str(a) for a in [*args, "--voxel-size", "0.2", "-o", out]]
            )
            assert result.exit_code == 0, (name, result.stderr)
        depth = folder.write("d.png", _png(DEPTH))
        intrinsics = folder.write("K.json", K_JSON.encode())
        args = ["register", depth, folder.path / "depth.png", "--features", "fpfh"]
        args += ["--min-confidence", "0"]
        result = CliRunner().invoke(
            cli, [str(a) for a in [*args, "--voxel-size", "0.2", "--intrinsics", intrinsics]]
        )
        assert result.exit_code == 0, result.stderr
        folder.write("bench/kitchen-evaluation/gt.log", GT_LOG.encode())
        folder.benchmark_fragments()
        result = CliRunner().invoke(
            cli, ["eval-fmr", str(folder.path / "bench"), "--method", "identity", "--quiet"]
        )
        assert result.exit_code == 0, result.stderr
