"""The Python API (byoc_cli.api): lazy import, typed results, the CLI's results."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import byoc_cli
from byoc_cli.cli.main import cli
from byoc_cli.errors import InputError, RegistrationError, ShapeError
from byoc_cli.io import format_transform, read_transform, write_ply
from byoc_cli.pipeline import default_weights
from tests.pipeline._clouds import cube, moved


def test_importing_byoc_cli_imports_neither_torch_nor_open3d():
    code = (
        "import sys, byoc_cli; from byoc_cli import register, extract_features, Registrar; "
        "print('torch' in sys.modules, 'open3d' in sys.modules, 'click' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False", "False"]


def test_api_names_are_exported():
    assert set(byoc_cli.__all__) >= {"register", "extract_features", "load_weights", "Features"}
    with pytest.raises(AttributeError):
        byoc_cli.no_such_name  # noqa: B018


def test_register_arrays_gives_the_cli_transform(tmp_path):
    src = cube()
    tgt, _ = moved(src)
    result = byoc_cli.register(src, tgt, seed=5, max_points=2000)
    assert isinstance(result, byoc_cli.Registration)
    assert result.T_tgt_src.shape == (4, 4) and result.T_tgt_src.dtype == np.float64
    assert 0.0 <= result.confidence <= 1.0 and result.features == "byoc"
    assert result.weights_sha256 == default_weights.verify_default_weights()
    write_ply(tmp_path / "s.ply", src)
    write_ply(tmp_path / "t.ply", tgt)
    out = tmp_path / "T.txt"
    args = ["register", str(tmp_path / "s.ply"), str(tmp_path / "t.ply"), "-o", str(out)]
    res = CliRunner().invoke(cli, [*args, "--seed", "5", "--max-points", "2000"])
    assert res.exit_code == 0, res.output
    # the PLY stores float32: compare against the API on the same file
    from_files = byoc_cli.register(tmp_path / "s.ply", tmp_path / "t.ply", seed=5, max_points=2000)
    assert out.read_text() == format_transform(from_files.T_tgt_src)
    assert np.allclose(read_transform(out), from_files.T_tgt_src)


def test_workers_give_the_transform_of_one_thread_and_a_worker_may_register():
    src = cube()
    tgt, _ = moved(src)
    settings = {"seed": 2, "max_points": 2000}
    one = byoc_cli.Registrar(threads=1).register(src, tgt, **settings)
    registrar = byoc_cli.Registrar(threads=2)
    two = registrar.register(src, tgt, **settings)
    # called from one of its own workers, register runs in place instead of waiting on itself
    job = registrar.executor().submit(registrar.register, src, tgt, **settings)
    inside = job.result(timeout=600)
    assert np.array_equal(one.T_tgt_src, two.T_tgt_src)
    assert np.array_equal(one.T_tgt_src, inside.T_tgt_src)
    assert two.timings.keys() >= {"load", "features_src", "prepare_tgt", "refine", "total"}
    with pytest.raises(ValueError, match="threads"):
        byoc_cli.Registrar(threads=0)


def test_fpfh_registration_recovers_a_known_motion():
    src = cube(1)
    tgt, T = moved(src)
    result = byoc_cli.register(src, tgt, features="fpfh", seed=0)
    assert result.estimator == "ransac" and result.refine == "none"
    assert np.abs(result.T_tgt_src - T).max() < 0.05
    assert result.timings.keys() >= {"load", "features_src", "features_tgt", "total"}


def test_scale_keeps_the_input_units():
    src_mm = cube(1) * 1000
    tgt_mm, T = moved(cube(1))
    tgt_mm = tgt_mm * 1000
    with pytest.raises(InputError, match="millimetres"):  # a fixed voxel in metres
        byoc_cli.register(src_mm, tgt_mm, features="fpfh", voxel_size=None)
    result = byoc_cli.register(src_mm, tgt_mm, features="fpfh", scale=0.001)
    assert np.abs(result.T_tgt_src[:3, 3] - 1000 * T[:3, 3]).max() < 50  # mm
    auto = byoc_cli.register(src_mm, tgt_mm, features="fpfh")  # the auto voxel reads the units
    assert auto.voxel_choice["voxel_size"] == pytest.approx(auto.voxel_size)
    assert np.abs(auto.T_tgt_src[:3, 3] - 1000 * T[:3, 3]).max() < 50  # mm


def test_extract_features_and_registrar_reuse():
    registrar = byoc_cli.Registrar()
    feats = registrar.extract(cube())
    assert isinstance(feats, byoc_cli.Features)
    m = feats.points.shape[0]
    assert feats.feats.shape[0] == m and feats.feats.dtype == np.float32
    assert np.allclose(np.linalg.norm(feats.feats, axis=1), 1.0, atol=1e-5)
    assert np.array_equal(cube()[feats.point_index], feats.points)
    assert feats.voxel_size == registrar.choose_voxel(cube()).voxel_size and feats.scale == 1.0
    same = byoc_cli.extract_features(cube(), weights=byoc_cli.load_weights())
    assert np.array_equal(same.feats, feats.feats)
    other = byoc_cli.Registrar("fpfh").extract(cube())
    with pytest.raises(ValueError, match="same features"):
        registrar.match(feats, other)
    # extracted one at a time, two clouds may choose different auto voxels: match extracts
    # both again at the pair's voxel
    apart = registrar.extract(cube(1)[::3])
    assert apart.voxel_size != feats.voxel_size
    result = registrar.match(feats, apart)
    assert result.voxel_size == registrar.choose_voxel(cube(), cube(1)[::3]).voxel_size


@pytest.mark.parametrize(
    ("points", "error"),
    [
        (np.zeros((10, 2)), ShapeError),
        (np.full((10, 3), np.nan), ShapeError),
        (np.zeros((10, 3)), RegistrationError),
    ],
)
def test_bad_arrays_raise_typed_errors(points, error):
    with pytest.raises(error):
        byoc_cli.extract_features(points, features="fpfh")


def test_missing_file_is_an_input_error(tmp_path: Path):
    with pytest.raises(InputError, match=r"none\.ply"):
        byoc_cli.load_cloud(tmp_path / "none.ply")
    with pytest.raises(ValueError, match="features must be"):
        byoc_cli.Registrar("nope")


# ------------------------------------------------------------------ the documented API

DOCS_API = Path(__file__).resolve().parents[1] / "docs" / "pipelines.md"


def _documented_signatures() -> list[str]:
    lines = DOCS_API.read_text().splitlines()
    start = lines.index("<!-- api-signatures -->") + 2  # the marker, then the fence
    end = lines.index("```", start)
    return lines[start:end]


def _code_object(name: str):
    from byoc_cli import api

    obj = api
    for part in name.split("."):
        obj = getattr(obj, part)
    return obj


def _check_signature(line: str) -> None:
    import ast
    import inspect

    from byoc_cli.pipeline.engine_recipe import FROM_RECIPE

    head, _, returns = line.partition(" -> ")
    name, _, params = head.partition("(")
    documented = ast.parse(f"def f({params[:-1]}): pass").body[0].args
    actual = inspect.signature(_code_object(name))
    if "." in name:  # a method, read from its class: without self
        actual = actual.replace(parameters=list(actual.parameters.values())[1:])
    kinds = inspect.Parameter
    doc_params = (
        [(a, kinds.POSITIONAL_OR_KEYWORD) for a in documented.args]
        + ([(documented.vararg, kinds.VAR_POSITIONAL)] if documented.vararg else [])
        + [(a, kinds.KEYWORD_ONLY) for a in documented.kwonlyargs]
        + ([(documented.kwarg, kinds.VAR_KEYWORD)] if documented.kwarg else [])
    )
    defaults = dict(
        zip([a.arg for a in documented.args][::-1], documented.defaults[::-1], strict=False)
    )
    defaults.update(
        {
            a.arg: d
            for a, d in zip(documented.kwonlyargs, documented.kw_defaults, strict=True)
            if d is not None
        }
    )
    assert [(a.arg, k) for a, k in doc_params] == [
        (p.name, p.kind) for p in actual.parameters.values()
    ], line
    for parameter in actual.parameters.values():
        node = defaults.get(parameter.name)
        if node is None:
            assert parameter.default is inspect.Parameter.empty, (line, parameter.name)
        elif isinstance(node, ast.Name) and node.id == "RECIPE":
            assert parameter.default is FROM_RECIPE, (line, parameter.name)
        else:
            assert ast.literal_eval(node) == parameter.default, (line, parameter.name)
            assert type(ast.literal_eval(node)) is type(parameter.default), (line, parameter.name)
    if returns:
        annotation = str(actual.return_annotation)
        assert annotation.split(".")[-1] == returns, (line, annotation)


def test_the_documented_signatures_are_the_codes():
    lines = _documented_signatures()
    names = [line.partition("(")[0] for line in lines]
    assert set(names) >= {n for n in byoc_cli._API if n not in ("Features", "Registration")}
    assert {"Registrar.extract", "Registrar.match", "Registrar.register"} <= set(names)
    for line in lines:
        _check_signature(line)


def _bullet(start: str) -> str:
    text = " ".join(DOCS_API.read_text().split())
    begin = text.index(start) + len(start)
    return text[begin : text.index(" * ", begin)]


def test_the_documented_keywords_and_fields_are_the_codes():
    import re

    from byoc_cli import api

    def names(text: str) -> list[str]:
        return re.findall(r"`([A-Za-z_][A-Za-z_0-9]*)`", text)

    register_keys = {*api._REGISTRAR_KEYS, *api._LOAD_KEYS, *api._MATCH_KEYS, *api._INIT_KEYS}
    assert set(names(_bullet("* `register`'s `overrides`:"))) - {"Registrar"} == register_keys
    extract = set(names(_bullet("* `extract_features`' `overrides`:")))
    assert extract == {*api._REGISTRAR_KEYS, *api._LOAD_KEYS} - {"fallback"}
    fields = _bullet("* A `Registration` (a NamedTuple) holds")
    registration, _, features = fields.partition("; a `Features` holds")
    documented = [n for n in names(registration) if n not in ("byoc", "register")]
    documented = [n for n in documented if n != "gate"]
    assert documented[:3] == ["T_tgt_src", "confidence", "passed"]
    assert set(documented) - {"min_confidence"} == set(api.Registration._fields)
    assert set(names(features)) == set(api.Features._fields)


def test_a_registration_says_whether_it_passed_the_gate():
    rng = np.random.default_rng(0)
    n = 3000
    pts = rng.uniform(-1, 1, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    pts[np.arange(n), axis] = np.sign(pts[np.arange(n), axis])
    src, tgt = pts * np.array([1.5, 1.0, 0.8]), pts * np.array([1.5, 1.0, 0.8]) + 0.05
    common = {"features": "fpfh", "refine": "none", "seed": 0}
    result = byoc_cli.register(src, tgt, **common)
    assert result.passed == (result.confidence >= 0.45)
    strict = byoc_cli.Registrar(features="fpfh", fallback_below=1.0).register(src, tgt, seed=0)
    assert strict.confidence < 1.0 and strict.passed is False
