"""Configs: JSON round trip of every experiment's presets, overrides, scopes."""

import dataclasses
import importlib
import json
from pathlib import Path

import pytest

from motionflows.config import (
    DataConfig,
    Scope,
    TrainConfig,
    apply_overrides,
    from_dict,
    load_config,
    save_config,
    to_dict,
)

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(
    p.stem for p in (ROOT / "experiments").glob("*.py") if not p.stem.startswith("_")
)


def _module(name):
    try:
        return importlib.import_module(f"experiments.{name}")
    except Exception as err:  # another engineer's module mid-edit must not break this file
        pytest.skip(f"experiments.{name} does not import: {err}")


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_preset_round_trips_through_json(tmp_path, name):
    module = _module(name)
    assert {"paper", "quick"} <= set(module.PRESETS)
    for preset, config in module.PRESETS.items():
        assert dataclasses.is_dataclass(config) and type(config).__dataclass_params__.frozen
        assert isinstance(config.data, DataConfig) and isinstance(config.train, TrainConfig)
        save_config(tmp_path / "config.json", experiment=module.NAME, preset=preset, config=config)
        exp, pre, back = load_config(tmp_path / "config.json", module.Config)
        assert (exp, pre, back) == (module.NAME, preset, config)
        # an exact whole-window score, or only bounds (VAE-LSTM)
        assert "window" in module.SCOPES or all(s.bound for s in module.SCOPES.values())


def test_a_run_saved_before_root_smoothing_was_a_field_keeps_holdens_features(tmp_path):
    """Runs saved before ``data.root_sigma_s`` existed were trained on features whose root
    was smoothed over 0.05 s: loading one must keep that, not take today's default (its
    standardiser and weights would then be scored on other features without a word)."""
    module = _module("moglow")
    config = module.PRESETS["quick"]
    assert config.data.root_sigma_s == pytest.approx(1.0 / 3.0)
    path = tmp_path / "config.json"
    save_config(path, experiment=module.NAME, preset="quick", config=config)
    assert load_config(path, module.Config)[2] == config
    payload = json.loads(path.read_text())
    del payload["config"]["data"]["root_sigma_s"]
    path.write_text(json.dumps(payload))
    old = load_config(path, module.Config)[2]
    assert old.data.root_sigma_s == 0.05
    assert old == dataclasses.replace(
        config, data=dataclasses.replace(config.data, root_sigma_s=0.05)
    )
    assert module.PRESETS["paper"].data.root_sigma_s == 0.05  # the papers' data


def test_overrides_dotted_bare_and_errors():
    import experiments.baselines as b

    c = apply_overrides(
        b.PRESETS["quick"],
        ["train.lr=0.5", "tau=3", "clip_norm=none", "data.mirror=false", "fit_windows=7"],
    )
    assert c.train.lr == 0.5 and c.tau == 3 and c.train.clip_norm is None
    assert c.data.mirror is False and c.fit_windows == 7
    with pytest.raises(ValueError, match="unknown config key"):
        apply_overrides(c, ["nope=1"])
    with pytest.raises(ValueError, match="cannot read"):
        apply_overrides(c, ["train.steps=many"])
    with pytest.raises(ValueError, match="key=value"):
        apply_overrides(c, ["train.steps"])
    with pytest.raises(ValueError, match="no field"):
        from_dict(TrainConfig, {"stepz": 3})
    # JSON written by an older version (fewer fields) still loads with the defaults
    d = to_dict(c)
    del d["train"]["min_lr_ratio"]
    assert from_dict(type(c), json.loads(json.dumps(d))) == c


def test_scope_scored_frames():
    class Cfg:
        tau = 10

    assert Scope("all").scored_frames(80) == 80
    assert Scope("official", skip="tau").scored_frames(80, Cfg()) == 70
    assert Scope("tail", skip=5).scored_frames(80) == 75
    with pytest.raises(ValueError, match="config"):
        Scope("official", skip="tau").scored_frames(80)


def test_overrides_parse_tuple_fields_with_element_types():
    @dataclasses.dataclass(frozen=True)
    class C:
        counts: tuple[int, ...] = (1,)
        pair: tuple[float, float] = (0.0, 1.0)
        width: int | None = None

    c = apply_overrides(C(), ["counts=[1,10,100]", "pair=0.5,2", "width=3"])
    assert c == C(counts=(1, 10, 100), pair=(0.5, 2.0), width=3)
    assert isinstance(c.counts[0], int) and isinstance(c.pair[0], float)
    assert apply_overrides(C(), ["counts=7,8"]).counts == (7, 8)
    with pytest.raises(ValueError, match="cannot read"):
        apply_overrides(C(), ["counts=[1,x]"])
    with pytest.raises(ValueError, match="cannot read"):
        apply_overrides(C(), ["pair=1"])  # wrong arity


def test_an_unreadable_value_names_its_type_for_people():
    """``K=abc`` says what K takes, not Python's repr of the type ("<class 'int'>")."""

    @dataclasses.dataclass
    class C:
        K: int = 4
        lr: float = 1e-3
        residual: bool = False

    for override, kind in (("K=abc", "a whole number"), ("lr=fast", "a number"),
                           ("residual=maybe", "true or false")):  # fmt: skip
        with pytest.raises(ValueError, match="cannot read") as err:
            apply_overrides(C(), [override])
        assert kind in str(err.value) and "<class" not in str(err.value), str(err.value)


def test_overrides_are_checked_together_not_one_at_a_time():
    """A preset's pair of fields that only make sense together (the Glow's
    ``residual_decay`` needs ``residual``) can be switched off in either order: the
    config is validated once, with every ``--set`` applied."""
    import experiments.glow_fixed as g

    preset = g.PRESETS["cpu"]
    assert preset.residual and preset.residual_decay != 1.0
    for order in (
        ["residual=false", "residual_decay=1.0"],
        ["residual_decay=1.0", "residual=false"],
    ):
        c = apply_overrides(preset, order)
        assert not c.residual and c.residual_decay == 1.0
    with pytest.raises(ValueError, match="needs residual=true"):
        apply_overrides(preset, ["residual=false"])  # the end state is still checked
    c = apply_overrides(preset, ["train.lr=0.5", "train.lr=0.25", "data.mirror=false"])
    assert c.train.lr == 0.25 and c.data.mirror is False  # the last --set of a key wins


@pytest.mark.parametrize(
    "experiment, item, needle",
    [
        ("moglow", "df=nan", "df must be"),
        ("moglow", "history_noise=inf", "history_noise must be"),
        ("moglow", "cond_embedding=-1", "cond_embedding must be"),
        ("vae_lstm", "elbo_samples=0", "elbo_samples must be"),
        ("vae_lstm", "l1_weight=-1", "l1_weight must be"),
        ("vae_lstm", "iwae_chunk=0", "iwae_chunk must be"),
        ("vae_lstm", "latent_dim=0", "latent_dim must be"),
        ("vae_lstm", "dropout=1.0", "dropout must be"),
        ("glow_fixed", "coupling_eps=nan", "coupling_eps must be"),
        ("baselines", "ridge=nan", "ridge must be"),
        ("baselines", "tau=100", "tau must be less than data.window"),
        ("baselines", "fit_windows=0", "fit_windows must be"),
        ("baselines", "model=foo", "model must be one of"),
        ("baselines", "covariance=foo", "covariance must be one of"),
        ("baselines", "train.seed=100000000000000000000000", "train.seed must be"),
    ],
)
def test_model_fields_that_cannot_train_are_refused_by_the_config(experiment, item, needle):
    """Each of these was accepted and then trained NaN steps, crashed at the first
    validation (after config.json was written), fitted one batch, or raised a raw
    traceback: the config refuses it before anything runs."""
    preset = _module(experiment).PRESETS["quick"]
    with pytest.raises(ValueError, match=needle):
        apply_overrides(preset, [item])


def test_data_short_pads_or_drops_takes_shorter_than_the_window():
    """``data.short`` reaches the data layer: 1.5 s synthetic takes in 2 s windows are padded
    (frozen tails, ``valid`` False there) or dropped (then there is nothing to train on)."""
    from motionflows.errors import MotionDataError

    short = DataConfig(synthetic_clips=12, synthetic_seconds=1.5, window=40, hop=10)
    padded = short.load().split("train")
    assert len(padded) > 0 and not padded.valid.all()
    with pytest.raises(MotionDataError, match="no training windows"):
        dataclasses.replace(short, short="drop").load()
    with pytest.raises(ValueError, match="data.short must be 'pad' or 'drop'"):
        DataConfig(short="crop")
    assert DataConfig().short == "pad"  # runs saved before the field keep their padding
