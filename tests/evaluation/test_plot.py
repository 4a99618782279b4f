"""Plots: titles name the data sets, axes reach the identity's error, legends use the
method names of the table."""

from __future__ import annotations

import numpy as np

from byoc_cli.evaluation.plot import accuracy_curve, fmr_figure, pairs_figure, plot_pairs

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _pairs_report() -> dict:
    errors = {"rotation_error_deg": 3.0, "translation_error_cm": 4.0, "chamfer": 1.0}
    identity = {"rotation_error_deg": 70.0, "translation_error_cm": 120.0, "chamfer": 30.0}
    return {
        "num_pairs": 1,
        "results": {"identity": {}, "fpfh-ransac": {}},
        "sources": [{"kind": "rgbd", "name": "tum_fr1_xyz", "root": "/data/rgbd/tum_fr1_xyz"}],
        "pairs": [
            {
                "gt_rotation_deg": 70.0,
                "gt_translation_cm": 120.0,
                "methods": {"identity": identity, "fpfh-ransac": errors},
            }
        ],
    }


def test_pairs_plot_names_the_data_and_reaches_the_identity_error(tmp_path):
    fig = pairs_figure(_pairs_report())
    assert "tum_fr1_xyz" in fig._suptitle.get_text()
    rotation, translation, _ = fig.axes
    assert translation.get_lines()[0].get_xdata().max() >= 120.0
    assert rotation.get_lines()[0].get_xdata().max() >= 70.0
    # the identity reaches 100 % within the axis
    identity = next(line for line in translation.get_lines() if line.get_label() == "identity")
    assert identity.get_ydata()[-1] == 100.0
    path = plot_pairs(_pairs_report(), tmp_path / "p.png")
    assert path.read_bytes().startswith(PNG_MAGIC)


def test_small_motions_keep_the_default_axes():
    report = _pairs_report()
    report["pairs"][0]["gt_translation_cm"] = 12.0
    report["pairs"][0]["gt_rotation_deg"] = 4.0
    rotation, translation, _ = pairs_figure(report).axes
    assert translation.get_lines()[0].get_xdata().max() == 50.0
    assert rotation.get_lines()[0].get_xdata().max() == 45.0


def test_fmr_plot_legends_use_method_names_and_title_names_the_benchmark():
    methods = [
        {"name": "fpfh-ransac", "features": {"key": "fpfh"}},
        {"name": "fpfh-procrustes", "features": {"key": "fpfh"}},
        {"name": "identity", "features": None},
    ]
    per_method = {"rmse_m": 0.1, "rotation_error_deg": 2.0}
    report = {
        "num_pairs": 1,
        "methods": methods,
        "settings": {"tau2": 0.05, "root": "/data/3DMatch", "scenes_selected": ["kitchen"]},
        "pairs": [
            {
                "official": True,
                "has_info": True,
                "features": {"fpfh": {"inlier_ratio": 0.2}},
                "methods": {m["name"]: per_method for m in methods},
            }
        ],
    }
    fig = fmr_figure(report)
    assert "3DMatch (kitchen)" in fig._suptitle.get_text()
    fmr_labels = [text.get_text() for text in fig.axes[0].get_legend().get_texts()]
    assert fmr_labels == ["fpfh-ransac, fpfh-procrustes"]
    rotation_labels = [text.get_text() for text in fig.axes[2].get_legend().get_texts()]
    assert rotation_labels == ["fpfh-ransac", "fpfh-procrustes", "identity"]


def test_accuracy_curve_counts_strictly_below():
    assert np.allclose(
        accuracy_curve([1.0, None, 3.0], np.array([1.0, 2.0, 4.0])), [0, 100 / 3, 200 / 3]
    )
