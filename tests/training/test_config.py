import json

import pytest

from byoc_cli.errors import InputError
from byoc_cli.training.config import (
    TrainConfig,
    config_from_json,
    config_keys,
    load_config_file,
    resolve_config,
)


def test_paper_defaults():
    c = TrainConfig()
    assert (c.lr, c.adam_eps, c.weight_decay, c.batch_size, c.seed) == (1e-4, 1e-4, 1e-6, 8, 8)
    assert (c.view_spacing, c.val_every, c.arch, c.variant) == (20, 5000, "compact", "byoc")
    assert c.num_correspondences == 200 and c.voxel_size == 0.025 and c.image_size == 128


def test_precedence_defaults_file_flags(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('steps = 50\nlr = 0.001\nvariant = "byoc-geo"\nrgbd_dir = "data"\n')
    c = resolve_config(load_config_file(path), {"lr": 0.01, "seed": None})
    assert c.steps == 50  # file over default
    assert c.lr == 0.01  # flag over file
    assert c.seed == 8  # default (None flag ignored)
    assert c.variant == "byoc-geo" and c.rgbd_dir == ("data",)


def test_train_table_and_int_to_float(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[train]\nlr = 1\nnum_correspondences = 100\n")
    c = resolve_config(load_config_file(path))
    assert c.lr == 1.0 and isinstance(c.lr, float) and c.num_correspondences == 100


def test_misspelled_key_is_refused_with_hint(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("num_correspodances = 100\n")  # research-code bug 10.3
    with pytest.raises(InputError, match="did you mean 'num_correspondences'"):
        load_config_file(path)


@pytest.mark.parametrize(
    "text",
    [
        "steps = 'ten'\n",
        "steps = 1.5\n",
        "amp = 3\n",
        "steps = [\n",
        "pair_gaps = []\n",
        "round_gaps = [1.5]\n",
    ],
)
def test_bad_values(tmp_path, text):
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=str(path)):
        load_config_file(path)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load_config_file(tmp_path / "nope.toml")


def test_range_errors():
    with pytest.raises(ValueError, match="variant"):
        TrainConfig(variant="byoc-foo")
    with pytest.raises(ValueError, match="steps"):
        TrainConfig(steps=0)
    with pytest.raises(ValueError, match="round_steps"):
        TrainConfig(round_steps=-1)
    with pytest.raises(ValueError, match="round_gaps"):
        TrainConfig(round_gaps=(0,))
    with pytest.raises(ValueError, match="loss must be one of infonce, hardest-contrastive"):
        TrainConfig(loss="triplet")
    with pytest.raises(ValueError, match="pos_margin and neg_margin"):
        TrainConfig(pos_margin=1.5, neg_margin=1.4)
    with pytest.raises(ValueError, match="pos_margin and neg_margin"):
        TrainConfig(neg_margin=2.5)


def test_loss_from_a_file(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('loss = "hardest-contrastive"\nneg_margin = 1.2\n')
    config = TrainConfig(**load_config_file(path))
    assert (config.loss, config.pos_margin, config.neg_margin) == ("hardest-contrastive", 0.1, 1.2)
    path.write_text("loss = 3\n")
    with pytest.raises(InputError, match="'loss' must be a string"):
        load_config_file(path)


def test_round_gaps_from_a_file(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("round_steps = 500\nround_gaps = [90]\n")
    values = load_config_file(path)
    assert values == {"round_steps": 500, "round_gaps": (90,)}
    assert TrainConfig(**values).round_gaps == (90,)
    path.write_text("round_gaps = []\n")  # no wider gaps: later rounds re-pose the same gaps
    assert TrainConfig(**load_config_file(path)).round_gaps == ()


def test_json_round_trip(tmp_path):
    c = TrainConfig(rgbd_dir=("a", "b"), steps=3, amp=False, depth_scale=5000.0)
    (tmp_path / "config.json").write_text(json.dumps({"config": c.to_dict()}))
    assert config_from_json(tmp_path / "config.json") == c
    assert list(c.to_dict()) == config_keys()


def test_pair_min_fitness_from_a_file_reaches_the_self_posing(tmp_path):
    from byoc_cli.training.self_posed import pseudo_config

    path = tmp_path / "c.toml"
    path.write_text("pair_min_fitness = 0.15\npair_gaps = [10, 60, 120]\n")
    config = TrainConfig(**load_config_file(path))
    posing = pseudo_config(config)
    assert (posing.min_fitness, posing.gaps) == (0.15, (10, 60, 120))
    assert pseudo_config(TrainConfig()).min_fitness == 0.3  # the shipped recipe's
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="pair_min_fitness must be in"):
            TrainConfig(pair_min_fitness=bad)
