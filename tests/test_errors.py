"""require_open3d: open3d imported once, without its plotting helpers, and all of it later."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from byoc_cli.errors import DependencyError, require_open3d


def _fresh(code: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120
    )


def test_open3d_is_imported_without_its_plotting_helpers_and_they_still_import_later():
    run = _fresh(
        """
        import sys
        from byoc_cli.errors import require_open3d
        o3d = require_open3d()
        print("dash" in sys.modules, "open3d.visualization" in sys.modules,
              "visualization" in vars(o3d))
        assert callable(o3d.pipelines.registration.compute_fpfh_feature)
        import open3d.visualization as vis  # what a user of the API may do next
        print(callable(vis.draw_geometries), o3d.visualization is vis)
        """
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "False", "False", "True", "True"]


def test_the_package_gives_its_visualization_when_a_user_asks_for_it_after_byoc():
    run = _fresh(
        """
        import sys
        from byoc_cli.errors import require_open3d
        require_open3d()  # as byoc does in a registration of the Python API
        import open3d as o3d  # then the user's own code
        print("dash" in sys.modules, callable(o3d.visualization.draw_geometries))
        print("dash" in sys.modules, o3d.visualization is sys.modules["open3d.visualization"])
        try:
            o3d.no_such_thing
        except AttributeError as exc:
            print("AttributeError", "no_such_thing" in str(exc))
        """
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["False", "True", "True", "True", "AttributeError", "True"]


def test_open3d_imported_from_two_threads_at_once_is_one_module():
    run = _fresh(
        """
        from concurrent.futures import ThreadPoolExecutor
        from byoc_cli.errors import require_open3d
        with ThreadPoolExecutor(4) as pool:
            found = list(pool.map(lambda _: require_open3d(), range(4)))
        import sys
        print(len({id(m) for m in found}), "open3d.visualization" in sys.modules)
        """
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["1", "False"]


def test_an_open3d_that_cannot_be_imported_is_a_dependency_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)
    with pytest.raises(DependencyError, match="pip install open3d"):
        require_open3d()
    left = sys.modules.get("open3d.visualization")  # no placeholder (it has no file) left
    assert left is None or getattr(left, "__file__", None)
