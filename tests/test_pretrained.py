"""The pretrained policies shipped with the package load, name their env, and still do
the task they were trained on (a shipped file that no longer fits its env fails here)."""

from __future__ import annotations

import json

import pytest

from heml_gym.agents.cli import main
from heml_gym.agents.export import PRETRAINED, OnnxPolicy
from heml_gym.envs import ENV_IDS

SHIPPED = sorted(PRETRAINED.glob("*.onnx"))


def test_every_env_has_a_pretrained_policy():
    assert sorted("heml_gym/" + p.stem for p in SHIPPED) == sorted(ENV_IDS)


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_a_pretrained_policy_does_its_task(path, capsys):
    policy = OnnxPolicy(path)
    assert policy.env_id == "heml_gym/" + path.stem
    assert main(["eval", "pretrained", "--env", policy.env_id, "--episodes", "5", "--seed", "777"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["env"] == policy.env_id and result["success_rate"] >= 0.8


def test_rollout_pretrained_records(tmp_path):
    assert main(["rollout", "--policy", "pretrained", "--episodes", "1", "--rrd", str(tmp_path / "r.rrd")]) == 0
    assert (tmp_path / "r.rrd").stat().st_size > 0


def test_eval_on_a_held_out_stiffness_range(tmp_path, capsys):
    """`heml-gym eval --physics` runs the episodes on other tissue (a train / test split of
    stiffness): the episodes' Young's moduli, as the env reports them at reset, lie in the
    given range and not in the task's own; a bad range is a one-line error."""
    import json

    from heml_gym.agents.cli import main

    out = tmp_path / "eval.json"
    assert main(["eval", "pretrained", "--episodes", "3", "--physics", '{"young_modulus": [12000, 16000]}',
                 "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    lo, hi = result["young_modulus_range"]
    assert 12000 <= lo <= hi <= 16000
    assert main(["eval", "pretrained", "--episodes", "1", "--physics", '{"young_modulus": [-1, 2]}']) == 2
    assert "--physics" in capsys.readouterr().err


def test_a_policy_for_a_retired_version_with_the_same_state_task(tmp_path, capsys):
    """A state policy exported for OrganRetraction-v1 (v2 changed only the camera's
    images) runs on v2 and its success there is v2's; on another task it is refused with a
    one-line error naming both envs."""
    import onnx

    from heml_gym.agents.export import exported_policy, pretrained_path
    from heml_gym.envs import ORGAN_RETRACTION, SAME_STATE_TASK, TISSUE_RETRACTION

    retired = "heml_gym/OrganRetraction-v1"
    assert SAME_STATE_TASK[retired] == ORGAN_RETRACTION
    model = onnx.load(pretrained_path(ORGAN_RETRACTION))
    for prop in model.metadata_props:
        if prop.key == "env_id":
            prop.value = retired
    old = tmp_path / "old.onnx"
    onnx.save(model, old)
    policy = exported_policy(str(old), ORGAN_RETRACTION, TISSUE_RETRACTION)
    assert policy.env_id == retired and policy.runs_on == ORGAN_RETRACTION
    with pytest.raises(ValueError, match="exported for heml_gym/OrganRetraction-v1"):
        exported_policy(str(old), TISSUE_RETRACTION, TISSUE_RETRACTION)
    assert main(["eval", str(old), "--episodes", "3", "--seed", "5"]) == 0  # (no --env: the successor)
    result = json.loads(capsys.readouterr().out)
    assert result["env"] == ORGAN_RETRACTION and result["success_rate"] >= 2 / 3
