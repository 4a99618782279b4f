"""Reading TOML whatever it holds: nesting, dotted keys and long numbers refused before
tomllib parses them, one message naming the key."""

from __future__ import annotations

import tomllib

import pytest

from byoc_cli.errors import InputError
from byoc_cli.io.tomlfile import MAX_DEPTH, MAX_KEY_PARTS, check_toml_shape, read_toml


@pytest.mark.parametrize(
    "text",
    [
        'preset = "byoc"\n[matching]\nmax_points = 3000\n',
        "[fitting]\ninlier_factor = 2.5e0\nnum_subsets = 1_000\n",
        "a.b.c = 1\n[x.y]\nz = [[1, 2], [3, 4]]\n",
        "[[runs]]\nname = 'a'\n[[runs]]\nname = 'b'\n",
        "t = { a = { b = [1, { c = 2 }] } }\n",
        's = "[[[[[[[[[[[[[[[[[[[[ a.b.c.d.e.f.g.h.i.j \\" ]"\n',
        "m = '''\n{{{{{{{{{{{{{{{{{{{{{{\n'''\n# [[[[[[[[[[[[[[[[[[[[ a.a.a.a.a.a.a.a.a.a\n",
        'q = """ ""\\"[[[[[[[[[[[[[[[[[[[[""" \n',
        "arr = [\n  [1],\n  [2],\n]\n[after]\nk = 1\n",
    ],
)
def test_ordinary_toml_passes_the_scan_and_parses(text):
    check_toml_shape(text)
    tomllib.loads(text)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("x = " + "[" * 50_000 + "]" * 50_000 + "\n", "x: nested deeper than 16 levels"),
        ("x = " + "{a = " * 60_000 + "1" + "}" * 60_000, "x: nested deeper than 16 levels"),
        (
            "[fitting]\nnum_subsets = " + "[" * 100_000 + "]" * 100_000,
            "fitting.num_subsets: nested deeper than 16 levels",
        ),
        (".".join(["a"] * 100_000) + " = 1\n", "key 'a.a.a.a.a.a.a.a' has more than 8 dotted"),
        ("[" + ".".join(["a"] * 100_000) + "]\n", "key 'a.a.a.a.a.a.a.a' has more than 8"),
        ("t = {" + ".".join(["b"] * 100) + " = 1}\n", "key 't' has more than 8 dotted parts"),
        ("seed = " + "9" * 5000 + "\n", "seed: a number of more than 64 digits"),
    ],
)
def test_hostile_shapes_are_refused_naming_the_key(text, message):
    with pytest.raises(ValueError, match="^" + message.replace("[", r"\[").replace(".", r"\.")):
        check_toml_shape(text)


def test_the_bounds_are_the_first_refused():
    check_toml_shape("x = " + "[" * MAX_DEPTH + "]" * MAX_DEPTH)
    with pytest.raises(ValueError):
        check_toml_shape("x = " + "[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1))
    check_toml_shape(".".join(["a"] * MAX_KEY_PARTS) + " = 1")
    with pytest.raises(ValueError):
        check_toml_shape(".".join(["a"] * (MAX_KEY_PARTS + 1)) + " = 1")


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"x = " + b"[" * 100_000 + b"]" * 100_000, "x: nested deeper than 16 levels"),
        (b"x = [1, 2", "is not TOML (Unclosed array"),
        (b"x = \xff\n", "is not UTF-8 text"),
        (b"x = 1\n" * 200_000, "larger than a recipe file may be (1 MiB)"),
    ],
)
def test_read_toml_is_one_input_error_naming_the_file(tmp_path, content, problem):
    path = tmp_path / "f.toml"
    path.write_bytes(content)
    with pytest.raises(InputError) as caught:
        read_toml(path, "recipe")
    text = str(caught.value)
    assert text.startswith(f"{path}: ") and problem in text and "\n" not in text, text
