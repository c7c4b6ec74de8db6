"""Pairwise relative skill (Cramer et al. 2022, as scoringutils computes it): a tournament worked
by hand, a model that forecast only some tasks, groups, and the vectorized form against the
literal algorithm (a merge per pair of models) on scores with holes."""
from __future__ import annotations

import itertools

import numpy as np
import pandas as pd
import pytest

from pipeline.evaluation.pairwise import PairwiseError, pairwise_comparison, relative_skill


def _scores(rows: dict[str, dict[str, float]]) -> pd.DataFrame:
    return pd.DataFrame([{"model_id": m, "task": t, "wis": w}
                         for m, tasks in rows.items() for t, w in tasks.items()])


# A forecasts t1..t4, B only t1, t2, the baseline C t1..t4. By hand:
# θ_AB = (1+2)/(2+2) = 3/4, θ_AC = 10/20 = 1/2, θ_BC = (2+2)/(2+4) = 2/3;
# θ_A = (1·3/4·1/2)^(1/3), θ_B = (4/3·1·2/3)^(1/3), θ_C = (2·3/2·1)^(1/3) = 3^(1/3);
# scaled: A = (1/8)^(1/3) = 1/2, B = (8/27)^(1/3) = 2/3, C = 1.
HAND = {"A": {"t1": 1, "t2": 2, "t3": 3, "t4": 4}, "B": {"t1": 2, "t2": 2},
        "C": {"t1": 2, "t2": 4, "t3": 6, "t4": 8}}


def test_tournament_worked_by_hand():
    result = pairwise_comparison(_scores(HAND), baseline="C")
    skill = result.skill.set_index("model_id")
    assert list(result.skill["model_id"]) == ["A", "B", "C"]          # best first
    np.testing.assert_allclose(skill["scaled_relative_skill"], [0.5, 2 / 3, 1.0], rtol=1e-12)
    np.testing.assert_allclose(skill["relative_skill"],
                               [0.375 ** (1 / 3), (8 / 9) ** (1 / 3), 3 ** (1 / 3)], rtol=1e-12)
    assert skill["n_forecasts"].tolist() == [4, 2, 4]
    np.testing.assert_allclose(skill["mean_score"], [2.5, 2.0, 5.0])
    ratios = result.ratios.set_index(["model_id", "compare_against"])
    assert ratios.loc[("A", "B"), "n_common"] == 2
    assert ratios.loc[("A", "B"), "mean_scores_ratio"] == pytest.approx(0.75)
    assert ratios.loc[("B", "A"), "mean_scores_ratio"] == pytest.approx(4 / 3)
    assert ratios.loc[("B", "B"), "mean_scores_ratio"] == 1.0 and len(ratios) == 9
    # the same without a baseline: θ only, no scaled column
    plain = pairwise_comparison(_scores(HAND))
    assert "scaled_relative_skill" not in plain.skill.columns
    assert relative_skill(_scores(HAND), baseline="A").set_index("model_id") \
        .loc["C", "scaled_relative_skill"] == pytest.approx(2.0)


def test_a_pair_without_common_forecasts_is_skipped():
    # D forecast only t5, which C also made but A and B did not: θ_D = (1·θ_DC)^(1/2)
    rows = {**HAND, "C": {**HAND["C"], "t5": 4}, "D": {"t5": 1}}
    result = pairwise_comparison(_scores(rows), baseline="C")
    ratios = result.ratios
    assert not ((ratios["model_id"] == "D") & ratios["compare_against"].isin(["A", "B"])).any()
    theta = result.skill.set_index("model_id")["relative_skill"]
    assert theta["D"] == pytest.approx((1 * 0.25) ** 0.5)
    # C now has 5 comparisons: θ_CA = 20/10 (t1..t4 only), θ_CB = 6/4, θ_CD = 4
    assert theta["C"] == pytest.approx((1 * 2 * 1.5 * 4) ** (1 / 4))


def test_groups_are_separate_tournaments():
    frame = pd.concat([_scores(HAND).assign(horizon=0),
                       _scores({m: {t: 2 * w for t, w in v.items()} for m, v in HAND.items()})
                       .assign(horizon=1),
                       _scores({"A": {"t1": 5}, "C": {"t1": 1}}).assign(horizon=2)])
    skill = relative_skill(frame, baseline="C", by=["horizon"])
    table = skill.pivot(index="model_id", columns="horizon", values="scaled_relative_skill")
    np.testing.assert_allclose(table[0].loc[["A", "B", "C"]], [0.5, 2 / 3, 1.0])
    np.testing.assert_allclose(table[1].loc[["A", "B", "C"]], [0.5, 2 / 3, 1.0])  # scale-free
    assert table[2]["A"] == pytest.approx(5.0) and np.isnan(table[2]["B"])
    with pytest.raises(PairwiseError, match="baseline 'B' has no scores in the group "
                                            r"\{'horizon': 2\}"):
        relative_skill(frame, baseline="B", by=["horizon"])


def _literal(scores: pd.DataFrame, baseline: str) -> pd.Series:
    """scoringutils' algorithm as written: a merge per pair, the ratio of sums, the geometric
    mean of the non-missing ratios (self included), divided by the baseline's."""
    models = sorted(scores["model_id"].unique())
    unit = ["round", "location", "horizon"]
    logs: dict[str, list[float]] = {m: [0.0] for m in models}
    for a, b in itertools.combinations(models, 2):
        both = scores[scores.model_id == a].merge(scores[scores.model_id == b], on=unit)
        if len(both):
            ratio = both["wis_x"].sum() / both["wis_y"].sum()
            logs[a].append(np.log(ratio))
            logs[b].append(-np.log(ratio))
    theta = pd.Series({m: np.exp(np.mean(v)) for m, v in logs.items()})
    return theta / theta[baseline]


def test_vectorized_tournament_equals_the_literal_algorithm_with_holes():
    rng = np.random.default_rng(7)
    grid = pd.MultiIndex.from_product([range(12), ["US", "06", "36", "48"], range(4)],
                                      names=["round", "location", "horizon"]).to_frame(index=False)
    frames = []
    for k, model in enumerate(["base", "m1", "m2", "m3", "m4", "m5"]):
        # holes: m2 only horizons 0-1, m3 only the last rounds, m4 only US, m5 a random half
        keep = {"base": np.ones(len(grid), bool), "m1": rng.random(len(grid)) < 0.9,
                "m2": grid.horizon.to_numpy() < 2, "m3": grid["round"].to_numpy() >= 8,
                "m4": (grid.location == "US").to_numpy(),
                "m5": rng.random(len(grid)) < 0.5}[model]
        scale = np.where(grid.location == "US", 50.0, 5.0)[keep]
        frames.append(grid[keep].assign(model_id=model,
                                        wis=scale * rng.gamma(2.0, 1.0 + 0.2 * k, keep.sum())))
    scores = pd.concat(frames, ignore_index=True).sample(frac=1.0, random_state=1)
    got = relative_skill(scores, baseline="base").set_index("model_id")["scaled_relative_skill"]
    want = _literal(scores, "base")
    np.testing.assert_allclose(got.loc[want.index], want, rtol=1e-12)
    by_h = relative_skill(scores, baseline="base", by=["horizon"])
    for h in range(4):
        part = by_h[by_h.horizon == h].set_index("model_id")["scaled_relative_skill"]
        want_h = _literal(scores[scores.horizon == h], "base")
        np.testing.assert_allclose(part.loc[want_h.index], want_h, rtol=1e-12)
    assert set(by_h[by_h.horizon == 3].model_id) == {"base", "m1", "m3", "m4", "m5"}
    # the scale of all scores and the order of rows change nothing
    again = relative_skill(scores.assign(wis=scores.wis * 7.5).iloc[::-1], baseline="base")
    np.testing.assert_allclose(again.set_index("model_id")["scaled_relative_skill"]
                               .loc[want.index], want, rtol=1e-12)


@pytest.mark.parametrize("mutate, match", [
    (lambda f: f.assign(wis=f.wis.where(f.index != 2, np.nan)), r"finite and >= 0; row 2"),
    (lambda f: f.assign(wis=f.wis.where(f.index != 0, -1.0)), r"finite and >= 0; row 0"),
    (lambda f: pd.concat([f, f.iloc[[1]]]), r"more than one score for"),
    (lambda f: f.drop(columns="task"), r"no forecast-unit column"),
    (lambda f: f.assign(wis=f.wis.where(f.model_id != "B", 0.0)), r"total 'wis' of 0"),
])
def test_scores_that_cannot_enter_a_tournament_are_refused(mutate, match):
    with pytest.raises(PairwiseError, match=match):
        pairwise_comparison(mutate(_scores(HAND)), baseline="C")
    with pytest.raises(PairwiseError, match="baseline 'Z' has no scores"):
        pairwise_comparison(_scores(HAND), baseline="Z")
