"""IDR on a policy type nobody here wrote: a FAKE third-party plugin (tests/doubles/policy_plugin,
discovered through its dist-info by lerobot's register_third_party_plugins), a stochastic policy
with no noise argument. The generic path runs the base's own processors and
predict_action_chunk, three passes under a forked RNG seeded alike."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from idr_core.sidecar import read_sidecar

from tests.lerobot_policy_idr.conftest import load, make_idr, obs_batch, seeded_chunks

PLUGIN_SITE = Path(__file__).resolve().parents[1] / "doubles" / "policy_plugin"


@pytest.fixture
def fake_sampler_base(tmp_path, monkeypatch) -> Path:
    """A checkpoint of the plugin's policy, found by lerobot's own plugin discovery."""
    monkeypatch.syspath_prepend(str(PLUGIN_SITE))
    from lerobot.configs import PreTrainedConfig
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()  # as lerobot's CLIs do at start
    assert "fake_sampler" in PreTrainedConfig.get_known_choices()
    from lerobot.policies.factory import get_policy_class

    from training.toy_checkpoints import _features, _stats, save_checkpoint

    inputs, outputs = _features(64, 8, 7, ("agentview",))
    cfg = PreTrainedConfig.get_choice_class("fake_sampler")(
        input_features=inputs, output_features=outputs, device="cpu"
    )
    torch.manual_seed(0)
    policy = get_policy_class("fake_sampler")(cfg)
    return save_checkpoint(policy, cfg, _stats(64, 8, 7, ("agentview",)), tmp_path / "base")


def _base(path: Path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    cfg = PreTrainedConfig.from_pretrained(path)
    policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg).eval()
    return policy, *make_pre_post_processors(cfg, pretrained_path=str(path))


def test_baseline_is_the_third_party_base_bit_for_bit(fake_sampler_base, tmp_path) -> None:
    folder = make_idr(fake_sampler_base, tmp_path / "idr", "--mode", "baseline")
    theirs_policy, pre0, post0 = _base(fake_sampler_base)
    policy, pre, post = load(folder)
    for t in range(6):
        obs = obs_batch(2, seed=t)
        torch.manual_seed(t)
        theirs = post0(theirs_policy.select_action(pre0(dict(obs))))
        torch.manual_seed(t)
        with torch.inference_mode():
            ours = post(policy.select_action(pre(dict(obs))))
        assert torch.equal(ours, theirs), t


def test_generic_path_shares_the_sampling_noise_by_forking_the_rng(
    fake_sampler_base, tmp_path
) -> None:
    """diagnose: the factual third is the base's own chunk under the same seed (three
    forwards of B rows each, so exactly equal); the three thirds see the same noise, so E_img
    and E_prop do not depend on the draw, and E_img > 0 when the image is zeroed."""
    folder = make_idr(
        fake_sampler_base, tmp_path / "idr", "--mode", "diagnose", "--diagnostics-dir",
        str(tmp_path / "d"),
    )  # fmt: skip
    idr = load(folder)
    policy = idr[0]
    assert policy.crn == "seeded_rng"
    chunks = seeded_chunks(idr, _base(fake_sampler_base), obs_batch(2, seed=0))
    assert all(torch.equal(ours, theirs) for ours, theirs in chunks)
    assert not torch.equal(chunks[0][0], chunks[1][0])  # the policy does sample
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    first, second = rows.iloc[:2], rows.iloc[2:]
    for key in ("e_img", "e_prop"):  # noise shared by the thirds: it cancels in the differences
        assert first[key].to_numpy() == pytest.approx(second[key].to_numpy(), rel=1e-5), key
    assert (rows["e_img"] > 0).all() and (rows["e_prop"] > 0).all()


def test_mode_E_refines_a_third_party_policy(fake_sampler_base, tmp_path) -> None:
    folder = make_idr(fake_sampler_base, tmp_path / "idr", "--tau", "1e9", "--no-clip")
    policy, pre, post = load(folder)
    base, pre0, post0 = _base(fake_sampler_base)
    obs = obs_batch(2, seed=3)
    with torch.inference_mode():
        ours = post(policy.predict_action_chunk(pre(dict(obs)), noise=torch.tensor([5])))
        torch.manual_seed(5)
        theirs = post0(base.predict_action_chunk(pre0(dict(obs))))[:, : policy.n_action_steps]
    assert torch.isfinite(ours).all() and not torch.equal(ours, theirs)  # the gate refined it


def test_a_type_no_installed_plugin_registers_is_refused_by_name(tmp_path) -> None:
    import json

    from lerobot_policy_idr.configuration_idr import IDRConfig, IDRConfigError

    base = tmp_path / "base"
    base.mkdir()
    (base / "config.json").write_text(json.dumps({"type": "nobody_registers_this"}))
    with pytest.raises(IDRConfigError, match=r"nobody_registers_this.*lerobot_policy_\* plugin"):
        IDRConfig(base_policy_path=str(base), mode="diagnose").resolve_base()
    (base / "config.json").write_text(json.dumps({"type": "tdmpc"}))
    with pytest.raises(IDRConfigError, match=r"tdmpc.*is refused.*select_action"):
        IDRConfig(base_policy_path=str(base), mode="diagnose").resolve_base()


def test_a_real_plugin_that_trains_at_test_time_is_refused_at_its_first_chunk(tmp_path) -> None:
    """lerobot-policy-act-ttt (from the package index): ACT whose vision backbone takes
    optimizer steps on every image it is shown, at inference too. IDR takes it on the generic
    path, and refuses it at the first chunk, before returning any action: its counterfactual rows
    would train the base, and the three passes would not run one network. Baseline (the base's
    own code path) runs it unchanged."""
    from lerobot_policy_idr.configuration_idr import IDRConfigError, is_third_party_type

    from training.toy_checkpoints import build_act_ttt

    base = build_act_ttt(tmp_path / "b")
    assert is_third_party_type("act_ttt")
    policy, pre, post = load(make_idr(base, tmp_path / "idr", "--mode", "diagnose"))
    refused = pytest.raises(IDRConfigError, match=r"'act_ttt'\) changed its own weights")
    with refused, torch.inference_mode():
        policy.predict_action_chunk(pre(obs_batch(2, seed=0)))
    policy, pre, post = load(make_idr(base, tmp_path / "idr_b", "--mode", "baseline"))
    with torch.inference_mode():
        assert torch.isfinite(post(policy.select_action(pre(obs_batch(2, seed=0))))).all()


def test_a_plugin_that_fails_to_import_is_named_with_its_own_error(tmp_path, monkeypatch) -> None:
    """A checkpoint of a type whose plugin raises at import (lerobot only logs it): the idr
    policy and idr-eval's lerobot backbone refuse it before loading, naming the plugin and its
    error."""
    import json

    from lerobot_policy_idr.configuration_idr import IDRConfig, IDRConfigError

    from workers.backbones.lerobot.checkpoint import check_checkpoint

    monkeypatch.syspath_prepend(str(PLUGIN_SITE.parent / "broken_policy_plugin"))
    base = tmp_path / "base"
    base.mkdir()
    (base / "config.json").write_text(json.dumps({"type": "fake_broken"}))
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(1)}, str(base / "model.safetensors"))
    want = r"lerobot_policy_fake_broken.*ModuleNotFoundError.*a_dependency_nobody_installed"
    with pytest.raises(IDRConfigError, match=want):
        IDRConfig(base_policy_path=str(base), mode="diagnose").resolve_base()
    with pytest.raises(
        ValueError, match=r"backbone.params.path: policy type 'fake_broken' .*" + want
    ):
        check_checkpoint(str(base))
