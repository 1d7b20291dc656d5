"""The TCR ablation figures end to end: a real (tiny) evaluation, then experiments.tcr_ablation on its directory."""

import json
import math
import shutil

import pytest
import torch
from safetensors.torch import load_file

from experiments.tcr_ablation import main
from firp.data import load_sequences
from firp.model.firp import FIRP, chunk_actions, chunk_frame_index
from firp.train import TrainConfig


@pytest.fixture(scope="module")
def evaluated(tiny_dataset, tmp_path_factory):
    """An evaluation directory with firp and firp_tcr trained for two epochs (one repeat)."""
    from firp.evaluate import main as evaluate

    root = tmp_path_factory.mktemp("ablation")
    out, cache = root / "eval", root / "cache"
    assert evaluate(["--data", str(tiny_dataset), "--repeats", "1", "--methods", "firp", "firp_tcr", "--epochs", "2",
                     "--threads", "1", "--image-size", "32", "--out", str(out), "--cache-dir", str(cache),
                     "--no-progress"]) == 0
    return out, cache


def _run(tiny_dataset, eval_dir, cache, out, *extra):
    return main(["--eval-dir", str(eval_dir), "--data", str(tiny_dataset), "--out", str(out), "--cache-dir", str(cache),
                 "--no-progress", "--tsne-episodes", "3", *extra])


def _final_distance_by_hand(eval_dir, tiny_dataset, cache, method: str, episode: int) -> float:
    """‖e_T − ê_T‖ from the RSSM's building blocks (eqs. 1-4 on means), not through score()/forward_train()."""
    ckpt = eval_dir / f"r0-{method}" / "checkpoint"
    cfg = TrainConfig.from_dict(json.loads((ckpt / "state.json").read_text())["config"])
    model = FIRP(cfg.model)
    model.load_state_dict(load_file(ckpt / "best.safetensors"))
    model.eval()
    data = load_sequences(tiny_dataset, cfg.model.encoder, cache, progress=False)
    feats, actions = data.features[episode:episode + 1], data.actions[episode:episode + 1]
    k, T = cfg.model.action_chunk, actions.shape[1]
    frames = chunk_frame_index(T, k)
    a = chunk_actions(model.action_norm(actions), k)
    rssm = model.rssm
    with torch.no_grad():
        e = model.projection(feats[:, frames])  # (1, Tc, E) real features of the observed frames
        h, s = rssm.initial_state(1, e.device)
        h = rssm.deter_step(h, s, a[:, 0])
        s, _ = rssm.posterior(h, e[:, 0])  # filtered from e_1 only
        for j in range(1, a.shape[1]):
            h = rssm.deter_step(h, s, a[:, j])
            s, _ = rssm.prior(h)
        e_hat_T = rssm.decode(s, h)
    return float(torch.linalg.vector_norm(e[0, -1] - e_hat_T[0]))


def test_ablation_figures_and_numbers(tiny_dataset, evaluated, tmp_path, capsys):
    eval_dir, cache = evaluated
    out = tmp_path / "figs"
    assert _run(tiny_dataset, eval_dir, cache, out) == 0
    for name in ("ablation.json", "ablation.md", "prediction_error.png", "prediction_error_by_step.png", "tsne.png"):
        assert (out / name).stat().st_size > 0, name
    report = json.loads((out / "ablation.json").read_text())
    assert [(m["repeat"], m["method"]) for m in report["models"]] == [(0, "firp"), (0, "firp_tcr")]
    for m in report["models"]:
        k = m["action_chunk"]
        assert k >= 1 and m["n_test"] == 4
        assert m["frame_index"] == chunk_frame_index(10, k)  # T = 10: one RSSM step per chunk of k plan steps
        assert len(m["frame_index"]) == math.ceil(10 / k)
        for values in m["per_episode"].values():
            assert len(values) == 4 and all(math.isfinite(v) for v in values)
        assert all(math.isfinite(m[k]) for k in ("scale", "spread", "r_ttc", "r_atc"))
        assert m["per_step"]["rel"][0] == pytest.approx(0.0, abs=1e-6)  # ê_1 is e_1
        # the weights and test episodes are the evaluated ones: the recorded test scores come out again
        assert m["recorded_score_max_abs_diff"] < 1e-4
    assert set(report["summary"]) == {"firp", "firp_tcr"}
    assert report["summary"]["firp_tcr"]["final_l2"]["n_repeats"] == 1
    assert report["tsne"]["repeat"] == 0 and len(report["tsne"]["episodes"]) == 3
    assert report["tsne"]["methods"] == ["firp", "firp_tcr"]
    md = (out / "ablation.md").read_text()
    assert "| FIRP + TCR | 1 | 4 |" in md and "python -m experiments.tcr_ablation --eval-dir" in md
    # the final-step distance of one episode, recomputed independently from the model's building blocks
    for m in report["models"]:
        episode = m["test_index"][1]
        expected = _final_distance_by_hand(eval_dir, tiny_dataset, cache, m["method"], episode)
        assert m["per_episode"]["final_l2"][1] == pytest.approx(expected, rel=1e-4, abs=1e-5)
        assert m["per_episode"]["final_rel"][1] == pytest.approx(expected / m["scale"], rel=1e-3, abs=1e-5)


def test_unfinished_checkpoints_are_skipped_with_a_message(tiny_dataset, evaluated, tmp_path, capsys):
    eval_dir, cache = evaluated
    copy = tmp_path / "eval"
    shutil.copytree(eval_dir, copy)
    state_path = copy / "r0-firp_tcr" / "checkpoint" / "state.json"
    state = json.loads(state_path.read_text())
    state_path.write_text(json.dumps({**state, "finished": False}))
    (copy / "r0-firp.json").unlink()  # trained, but the evaluation's row is missing
    with pytest.raises(SystemExit) as exc:
        _run(tiny_dataset, copy, cache, tmp_path / "figs")
    err = capsys.readouterr()
    assert exc.value.code == 2
    assert "r0-firp_tcr: skipped, training not finished" in err.out and "r0-firp: skipped" in err.out
    assert f"no finished FIRP-variant checkpoint in {copy}" in err.err
    state_path.write_text(json.dumps(state))  # firp_tcr finished again: runs on it alone
    assert _run(tiny_dataset, copy, cache, tmp_path / "figs") == 0
    report = json.loads((tmp_path / "figs" / "ablation.json").read_text())
    assert [m["method"] for m in report["models"]] == ["firp_tcr"] and len(report["skipped"]) == 1


def test_missing_or_empty_eval_dir_is_a_clear_cli_error(tiny_dataset, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--eval-dir", str(tmp_path / "nope"), "--data", str(tiny_dataset)])
    assert f"--eval-dir: {tmp_path / 'nope'} is not a directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit):
        main(["--eval-dir", str(tmp_path / "empty"), "--data", str(tiny_dataset)])
    assert f"no finished FIRP-variant checkpoint in {tmp_path / 'empty'}" in capsys.readouterr().err
