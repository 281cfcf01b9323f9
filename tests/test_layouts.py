"""Every maze layout's partitions (SPEC.md 2, 2.1), initial partitions for any box-state
environment, registered environments, saved partitions, and the new-maze example."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import envs
from gara_jax import boxes
from gara_jax import partition as part
from gara_jax.algorithms import GaraConfig, HandcraftedConfig, HiroConfig, make_algorithm
from gara_jax.algorithms.gara import initial_partition

LAYOUTS = tuple(part.LAYOUT_PARTITIONS)
#: Handcrafted boxes per layout (SPEC.md 2.1: labyrinth splits 2 rows into 2 and 2 into 4).
HANDCRAFTED_COUNTS = {"u_maze": 6, "four_rooms": 4, "u_maze_6": 6, "big_u_maze": 7,
                      "labyrinth": 15}
GARA_COUNTS = {"u_maze": 2, "four_rooms": 2, "u_maze_6": 2, "big_u_maze": 3, "labyrinth": 4}


def _space(layout):
    env, params = envs.make(layout)
    space = env.observation_space(params)
    return np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)


def test_every_layout_has_both_partitions():
    assert set(LAYOUTS) == set(envs.LAYOUTS)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_partitions_tile_or_cover_the_observation_space(layout):
    lo_s, hi_s = _space(layout)
    g_lo, g_hi = part.layout_boxes(layout, "gara")
    h_lo, h_hi = part.layout_boxes(layout, "handcrafted")
    assert len(g_lo) == GARA_COUNTS[layout] and len(h_lo) == HANDCRAFTED_COUNTS[layout]
    boxes.check_tiles(g_lo, g_hi, lo_s, hi_s)  # GARA refines a tiling
    if (layout, "handcrafted") in part.OVERLAPPING:
        boxes.check_covers(h_lo, h_hi, lo_s, hi_s)
        with pytest.raises(ValueError, match="overlap|volume"):
            boxes.check_tiles(h_lo, h_hi, lo_s, hi_s)
    else:
        boxes.check_tiles(h_lo, h_hi, lo_s, hi_s)


def test_labyrinth_handcrafted_splits_and_first_box_on_the_overlap():
    lo, hi = part.layout_boxes("labyrinth", "handcrafted")
    # Row 3 ([1,3]x[0.5,6], "vx,vy") becomes 4 boxes at indices 5..8, in the documented order.
    assert lo[5:9, :2].tolist() == [[1.0, 0.5]] * 4
    assert [tuple(lo[i, 2:]) + tuple(hi[i, 2:]) for i in range(5, 9)] == [
        (-1, -1, 0, 0), (-1, 0, 0, 1), (0, -1, 1, 0), (0, 0, 1, 1)]
    # The last row [5.5,6]x[0,6] is split in vy into the last two boxes.
    assert lo[13:, 3].tolist() == [-1.0, 0.0] and hi[13:, 3].tolist() == [0.0, 1.0]
    p = part.layout_partition("labyrinth", "handcrafted", max_goals=16)
    # A point of the shared strip [5.5,6]x[0,0.5] belongs to the first box holding it: the
    # "vx" half of [1,6]x[0,0.5] (index 3 for vx < 0, 4 for vx >= 0), not the [5.5,6] column.
    got = part.locate(p, np.array([[5.8, 0.2, -0.5, 0.3], [5.8, 0.2, 0.5, 0.3],
                                   [5.8, 3.0, 0.5, 0.3]], np.float32))
    assert np.asarray(got).tolist() == [3, 4, 14]


@pytest.mark.parametrize("layout", LAYOUTS)
def test_every_algorithm_initialises_on_every_layout(layout):
    capacity = max(HANDCRAFTED_COUNTS[layout], 6)
    configs = (GaraConfig(env=layout), HandcraftedConfig(env=layout, max_goals=capacity),
               HiroConfig(env=layout))
    n_goals = {}
    for cfg in configs:
        alg = make_algorithm(cfg)
        state = jax.eval_shape(alg.init, jax.random.key(0))  # traced, not compiled
        leaves = jax.tree.leaves(state)
        assert leaves and all(np.all(np.array(leaf.shape) >= 0) for leaf in leaves)
        if not isinstance(cfg, HiroConfig):
            n_goals[alg.name] = int(initial_partition(cfg).count)
    assert n_goals == {"gara": GARA_COUNTS[layout], "handcrafted": HANDCRAFTED_COUNTS[layout]}


def test_too_many_boxes_name_max_goals():
    with pytest.raises(part.PartitionFullError, match="max_goals"):
        initial_partition(HandcraftedConfig(env="labyrinth"))  # 15 boxes, default capacity 6
    lo, hi = part.layout_boxes("labyrinth", "handcrafted")
    with pytest.raises(ValueError, match="max_goals: 15 initial_boxes"):
        HandcraftedConfig(env="labyrinth", initial_boxes=(lo, hi))


def test_initial_boxes_are_validated_against_the_observation_space():
    lo, hi = part.state_space(3.0)
    half_hi = hi.copy()
    half_hi[0] = 1.5
    with pytest.raises(ValueError, match="initial_boxes: boxes do not cover"):
        initial_partition(GaraConfig(initial_boxes=([lo], [half_hi])))
    with pytest.raises(ValueError, match="initial_boxes: no box contains"):
        initial_partition(HandcraftedConfig(initial_boxes=([lo], [half_hi])))
    with pytest.raises(ValueError, match=r"initial_boxes: expected boxes of shape \[N, 4\]"):
        initial_partition(GaraConfig(initial_boxes=([[0.0, 0.0]], [[3.0, 3.0]])))
    with pytest.raises(ValueError, match="initial_boxes: must be a pair"):
        GaraConfig(initial_boxes=lo)
    with pytest.raises(ValueError, match="initial_boxes"):
        GaraConfig(initial_boxes=([lo], [lo - 1]))  # hi below lo
    with pytest.raises(ValueError, match="initial_boxes: box bounds must be finite"):
        GaraConfig(initial_boxes=([lo], [np.full(4, np.inf)]))
    # Overlapping boxes cover but do not tile: Handcrafted takes them, GARA refuses them.
    both = ([lo, lo], [hi, half_hi])
    assert int(initial_partition(HandcraftedConfig(initial_boxes=both)).count) == 2
    with pytest.raises(ValueError, match="initial_boxes"):
        initial_partition(GaraConfig(initial_boxes=both))


def test_initial_split_x_is_checked_against_the_layout():
    with pytest.raises(ValueError, match="initial_split_x"):
        GaraConfig(env="u_maze", initial_split_x=4.0)
    assert int(initial_partition(GaraConfig(env="u_maze_6", initial_split_x=4.0)).count) == 2
    with pytest.raises(ValueError, match="initial_split_x"):
        GaraConfig(initial_split_x=1.0, initial_boxes=part.layout_boxes("u_maze", "gara"))


def test_register_and_unknown_names():
    envs.register("u_maze_50_steps", lambda **o: envs.make("u_maze", **{"max_steps": 50, **o}))
    assert "u_maze_50_steps" in envs.names()
    assert envs.make("u_maze_50_steps")[1].max_steps == 50
    with pytest.raises(ValueError, match="built-in"):
        envs.register("u_maze", envs.make)
    with pytest.raises(ValueError, match="factory"):
        envs.register("x_maze", 3)
    with pytest.raises(ValueError, match="env: unknown environment 'x_maze'"):
        GaraConfig(env="x_maze")
    # A registered environment has no built-in partition: the error asks for the boxes.
    with pytest.raises(ValueError, match="initial_boxes: environment 'u_maze_50_steps' has no"):
        initial_partition(GaraConfig(env="u_maze_50_steps"))
    cfg = GaraConfig(env="u_maze_50_steps", initial_boxes=part.layout_boxes("u_maze", "gara"))
    assert int(initial_partition(cfg).count) == 2


def test_saved_partition_starts_another_run(tmp_path):
    """The transfer experiment's plumbing: save a partition, start a config from it."""
    p = part.layout_partition("labyrinth", "gara", max_goals=8)
    # Box 0 is [0,3]x[0,3]: cut it at x = 1.5, as a split would.
    p, _ = part.replace_box(p, 0, np.array([[0, 0, -1, -1], [1.5, 0, -1, -1]], np.float32),
                            np.array([[1.5, 3, 1, 1], [3, 3, 1, 1]], np.float32))
    path = tmp_path / "partition.json"
    part.save_boxes(path, p)
    data = json.loads(path.read_text())
    assert len(data["lo"]) == 5
    cfg = GaraConfig(env="labyrinth", initial_boxes=part.load_boxes(path))
    again = initial_partition(cfg)
    np.testing.assert_array_equal(np.asarray(again.boxes()[0]), np.asarray(p.boxes()[0]))
    path.write_text(json.dumps({"lo": []}))
    with pytest.raises(ValueError, match="keys 'lo' and 'hi'"):
        part.load_boxes(path)


@settings(max_examples=60, deadline=None)
@given(cuts=st.lists(st.sampled_from([0.5, 1.0, 1.5, 2.0, 2.5]), min_size=0, max_size=3,
                     unique=True),
       drop=st.integers(0, 8), grow=st.integers(0, 8))
def test_check_covers_agrees_with_dense_sampling(cuts, drop, grow):
    """Boxes from a grid over [0,3]^2, one possibly dropped and one possibly grown into its
    neighbour: ``check_covers`` passes exactly when every point of a fine grid is covered."""
    edges = np.array(sorted({0.0, 3.0, *cuts}))
    lo = np.array([(a, b) for a in edges[:-1] for b in edges[:-1]], np.float64)
    hi = np.array([(a, b) for a in edges[1:] for b in edges[1:]], np.float64)
    if drop < len(lo) and len(lo) > 1:
        lo, hi = np.delete(lo, drop, 0), np.delete(hi, drop, 0)
    if grow < len(lo):
        hi[grow] = np.minimum(hi[grow] + 0.5, 3.0)  # overlaps its neighbour: still a cover
    fine = np.linspace(0.05, 2.95, 30)
    points = np.stack(np.meshgrid(fine, fine, indexing="ij"), -1).reshape(-1, 2)
    covered = np.all(np.any(np.all((lo <= points[:, None]) & (points[:, None] <= hi), -1), -1))
    try:
        boxes.check_covers(lo, hi, [0.0, 0.0], [3.0, 3.0])
        passed = True
    except ValueError as err:
        assert "no box contains the point" in str(err)
        passed = False
    assert passed == covered


def _example():
    path = Path(__file__).resolve().parents[1] / "examples" / "new_maze.py"
    spec = importlib.util.spec_from_file_location("new_maze_example", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_new_maze_example_runs(tmp_path):
    example = _example()
    out = example.main(["--seeds", "2", "--steps", "600", "--steps-per-epoch", "300",
                        "--out", str(tmp_path)])
    assert out["training"]["n"] == 2 and out["greedy"]["n"] == 2
    assert 0.0 <= out["greedy"]["mean"] <= 1.0
    assert all(g >= 2 for g in out["goals"]) and out["seed_drawn"] in (0, 1)
    saved = part.load_boxes(tmp_path / "final_partition.json")
    assert len(saved[0]) in out["goals"]
    # The saved boxes tile the zigzag maze's observation space (they can start another run).
    env, params = example.make_zigzag()
    space = env.observation_space(params)
    boxes.check_tiles(np.array(saved[0]), np.array(saved[1]), space.low, space.high)
    assert (tmp_path / "partition.png").stat().st_size > 0


def test_reproduce_takes_every_layout_with_its_budget(capsys):
    from experiments import u_maze

    assert set(u_maze.ENVS) == {*envs.LAYOUTS, "point_u_maze"} == set(u_maze.ENV_STEPS)
    cfg = u_maze.method_config("handcrafted", env="labyrinth")
    assert cfg.max_goals == 15 and int(initial_partition(cfg).count) == 15
    assert u_maze.main(["--env", "u_maze_6", "--methods", "all", "--dry-run"]) == 0
    plan = capsys.readouterr().out
    assert "environment: u_maze_6" in plan
    assert f"steps: {u_maze.ENV_STEPS['u_maze_6']:,} per seed" in plan


def test_mazes_study_quick_run_writes_its_files(tmp_path, capsys):
    from experiments import mazes

    assert mazes.main(["--dry-run", "--seeds", "3"]) == 0
    plan = capsys.readouterr().out
    assert plan.count("\n") == 1 + len(mazes.MAZES) * len(mazes.METHODS)
    argv = ["--quick", "--steps", "1000", "--mazes", "four_rooms", "--no-progress",
            "--methods", "gara,gara_no_refinement", "--out", str(tmp_path)]
    assert mazes.main(argv) == 0
    runs = json.loads((tmp_path / "mazes.json").read_text())["runs"]["four_rooms"]
    assert set(runs) == {"gara", "gara_no_refinement"}
    assert runs["gara_no_refinement"]["config"]["min_steps"] == 10**9
    assert all("commit" in run for run in runs.values())  # None outside a git checkout
    for run in runs.values():
        s = run["summary"]
        assert s["greedy_end"]["n"] == 2 and len(s["per_seed"]["greedy_last10"]) == 2
        assert len(run["final_partitions"]) == 2
        assert len(s["curves"]["env_steps"]) == 1 and len(s["curves"]["train"]) == mazes.CURVE_POINTS
    assert runs["gara_no_refinement"]["summary"]["splits"] == 0.0
    table = (tmp_path / "table.md").read_text()
    assert "gara − no refinement (paired)" in table and "| four_rooms | `gara` | 1,000 |" in table
    for name in ("mazes_success.png", "mazes_partitions.png"):
        assert (tmp_path / name).stat().st_size > 0
    # A second call finds both runs in mazes.json and trains nothing again.
    before = (tmp_path / "mazes.json").stat().st_mtime_ns
    assert mazes.main(argv) == 0
    assert (tmp_path / "mazes.json").stat().st_mtime_ns == before
    # Another block of seeds is stored beside the first and pooled with it.
    argv[argv.index("gara,gara_no_refinement")] = "gara_no_refinement"
    assert mazes.main(argv + ["--first-seed", "5"]) == 0
    runs = json.loads((tmp_path / "mazes.json").read_text())["runs"]["four_rooms"]
    assert runs["gara_no_refinement@seeds5-6"]["first_seed"] == 5
    assert mazes.pooled(runs, "gara_no_refinement")[0] == [0, 1, 5, 6]
    assert "| four_rooms | `gara_no_refinement` | 4 |" in (tmp_path / "table.md").read_text()


def test_pooled_table_pairs_over_the_seeds_both_methods_have():
    from experiments import mazes

    def run(greedy, first=0):
        ci = {"mean": float(np.mean(greedy)), "ci95": 0.0, "n": len(greedy)}
        train = [1.0] * len(greedy)  # training success 1 in every seed: 1.00 ± 0.00 pooled
        return {"seeds": len(greedy), "first_seed": first,
                "summary": {"per_seed": {"greedy_last10": greedy, "train_last30k": train},
                            "greedy_last10": ci}}

    runs = {"big_u_maze": {"gara": run([1.0, 0.0]), "gara@seeds2-3": run([1.0, 0.5], 2),
                           "gara_no_refinement": run([0.0, 0.0]),
                           "gara_no_refinement@seeds3-3": run([0.5], 3),
                           "handcrafted": run([1.0, 1.0])}}
    rows = mazes.pooled_table(runs).splitlines()
    # gara's greedy over seeds 0-3: 0.625, sd 0.48, t(0.975, 3) = 3.18; paired with
    # refinement off over seeds 0, 1, 3: (1, 0, 0).
    assert len(rows) == 4 and rows[2].startswith(
        "| big_u_maze | `gara` | 4 | 1.00 ± 0.00 | 0.62 ± 0.76 | `gara_no_refinement` | 3 "
        "| 0.33 ± 1.43 |")
    assert "| `gara_no_refinement` | 3 | 1.00 ± 0.00 | 0.17 ± 0.72 | - | 0 | - |" in rows[3]
    assert mazes.pooled_table({"big_u_maze": {"gara": run([1.0])}}) == ""
    runs["big_u_maze"]["gara@seeds1-1"] = run([0.0], 1)
    with pytest.raises(ValueError, match="overlap"):
        mazes.pooled(runs["big_u_maze"], "gara")
    with pytest.raises(SystemExit):
        mazes.parse_args(["--first-seed", "-1"])


def test_mazes_study_rejects_bad_names():
    from experiments import mazes

    with pytest.raises(SystemExit):
        mazes.parse_args(["--mazes", "x_maze"])
    with pytest.raises(SystemExit):
        mazes.parse_args(["--methods", "gara,gara"])
    with pytest.raises(ValueError, match="method"):
        mazes.method_config("hiro_x", "u_maze")


def test_variant_table_pairs_each_variant_with_refinement_off_and_gara():
    from experiments import mazes

    def run(greedy):
        ci = {"mean": float(np.mean(greedy)), "ci95": 0.0, "n": len(greedy)}
        return {"summary": {"per_seed": {"greedy_last10": greedy}, "greedy_last10": ci,
                            "train_last30k": ci, "goals_end": 3.0, "splits": 0.5}}

    runs = {"u_maze": {"gara": run([0.5, 0.5]), "gara_no_refinement": run([0.25, 0.75]),
                       "gara+one_cut": run([1.0, 1.0])},
            "labyrinth": {"gara": run([1.0, 1.0])}}
    text = mazes.variant_table(runs)
    row = next(line for line in text.splitlines() if "gara+one_cut" in line)
    # 1 - (0.25, 0.75) = (0.75, 0.25): mean 0.50, interval t(0.975, 1) x 0.354 / sqrt(2) = 3.18.
    assert row.startswith("| u_maze | `gara+one_cut` | 1.00 ± 0.00 | 1.00 ± 0.00 | 0.50 ± 3.18 "
                          "| 0.50 ± 0.00 | 3.0 | 0.5 |")
    assert "labyrinth" not in text and mazes.variant_table({"u_maze": {}}) == ""
    # A gara variant pairs with the refinement-off agent that has the same change; a variant of
    # another base pairs with that base and has no refinement-off comparison.
    runs["u_maze"].update({"gara+no_filler_goal": run([1.0, 0.5]),
                           "gara_no_refinement+no_filler_goal": run([0.5, 0.5]),
                           "handcrafted+no_filler_goal": run([1.0, 1.0]),
                           "handcrafted": run([0.5, 1.0])})
    rows = {line.split("|")[2].strip(): line for line in mazes.variant_table(runs).splitlines()}
    assert "| 0.25 ± 3.18 | 0.25 ± 3.18 |" in rows["`gara+no_filler_goal`"]
    assert "| - | 0.25 ± 3.18 |" in rows["`handcrafted+no_filler_goal`"]
    assert "| - | 0.00 ± 3.18 |" in rows["`gara_no_refinement+no_filler_goal`"]
    off = mazes.method_config("gara_no_refinement+no_filler_goal", "big_u_maze")
    hand = mazes.method_config("handcrafted+no_filler_goal", "big_u_maze")
    assert (off.min_steps, off.non_targets) == (10**9, "layout")
    assert type(hand).__name__ == "HandcraftedConfig" and hand.max_goals == 7


def test_handcrafted_boxes_variant_takes_each_mazes_authors_partition():
    from experiments import mazes
    from gara_jax import partition
    from gara_jax.algorithms.gara import GaraConfig, HandcraftedConfig

    for maze in ("u_maze", "big_u_maze"):
        off = mazes.method_config("gara_no_refinement+handcrafted_boxes", maze)
        lo, hi = partition.layout_boxes(maze, "handcrafted")
        assert np.array_equal(np.array(off.initial_boxes[0]), lo)
        assert np.array_equal(np.array(off.initial_boxes[1]), hi)
        assert off.min_steps == 10**9 and type(off) is GaraConfig
        # With refinement off it is Handcrafted but for GARA's entry reward.
        hand = mazes.method_config("handcrafted", maze)
        assert isinstance(hand, HandcraftedConfig)
        assert (off.entry_reward, hand.entry_reward) == ("previous_plus_one", "constant")
    assert len(mazes.method_config("gara+handcrafted_boxes", "u_maze").initial_boxes[0]) == 6
    with pytest.raises(ValueError, match="overlap"):  # the labyrinth's boxes do not tile
        mazes.method_config("gara_no_refinement+handcrafted_boxes", "labyrinth")
    with pytest.raises(SystemExit):  # refused before anything is trained
        mazes.parse_args(["--mazes", "u_maze,labyrinth", "--methods", "gara+handcrafted_boxes"])


def test_table_pairs_gara_and_handcrafted_with_refinement_off_seed_by_seed():
    from experiments import mazes

    def run(greedy):
        ci = {"mean": float(np.mean(greedy)), "ci95": 0.0, "n": len(greedy)}
        per_seed = {k: greedy for k in ("train_ep300_400", "train_last30k", "greedy_end",
                                        "greedy_last10")}
        return {"steps": 10, "summary": {"per_seed": per_seed, "train_ep300_400": ci,
                                         "train_last30k": ci, "greedy_end": ci,
                                         "greedy_last10": ci, "goals_end": 2.0,
                                         "analysed": 0.0, "splits": 0.0}}

    runs = {"u_maze": {"gara": run([0.5, 0.5]), "gara_no_refinement": run([0.25, 0.75]),
                       "handcrafted": run([1.0, 0.5])}}
    rows = {line.split("|")[2].strip(): line for line in mazes.table(runs).splitlines()}
    # (1.0, 0.5) - (0.25, 0.75) = (0.75, -0.25): mean 0.25, t(0.975, 1) x 0.707 / sqrt(2) = 6.35.
    assert rows["handcrafted − no refinement (paired)"].count("0.25 ± 6.35") == 4
    assert rows["gara − no refinement (paired)"].count("0.00 ± 3.18") == 4
    del runs["u_maze"]["gara_no_refinement"]
    assert "(paired)" not in mazes.table(runs)


def test_handcrafted_cuts_split_the_exit_goal_or_the_others_and_tile():
    from envs.layouts import layout_spec
    from experiments import mazes
    from gara_jax import partition

    def rows(boxes):
        return {tuple(a[:2]) + tuple(b[:2]) for a, b in zip(*boxes)}

    hand = rows(partition.layout_boxes("u_maze", "handcrafted"))
    exit_cut = rows(mazes.handcrafted_cuts("u_maze", "exit_goal"))
    other_cut = rows(mazes.handcrafted_cuts("u_maze", "other_goals"))
    assert (0.0, 0.0, 1.0, 3.0) in exit_cut and (1.0, 0.0, 3.0, 3.0) in other_cut
    assert (exit_cut - {(0.0, 0.0, 1.0, 3.0)}) | (other_cut - {(1.0, 0.0, 3.0, 3.0)}) == hand
    for maze in ("four_rooms", "u_maze_6", "big_u_maze"):
        lo_s, hi_s = partition.state_space(layout_spec(maze)["n"])
        for where in ("exit_goal", "other_goals"):
            lo, hi = mazes.handcrafted_cuts(maze, where)
            partition.from_boxes(lo, hi, lo_s, hi_s)  # raises unless they tile
        lo, hi = mazes.start_goal_halves(maze)
        partition.from_boxes(lo, hi, lo_s, hi_s)
    cfg = mazes.method_config("gara_no_refinement+hand_cut_exit_goal", "big_u_maze")
    assert len(cfg.initial_boxes[0]) == 6 and cfg.min_steps == 10**9
    with pytest.raises(ValueError, match="maze"):
        mazes.handcrafted_cuts("labyrinth", "exit_goal")
    with pytest.raises(ValueError, match="where"):
        mazes.handcrafted_cuts("u_maze", "exit")


def test_split_log_keeps_each_seeds_splits_in_order_and_drops_other_verdicts():
    from types import SimpleNamespace

    from experiments.mazes import analysis_counts, split_log

    box = [[0.0, 0.0, -1.0, -1.0], [3.0, 3.0, 1.0, 1.0]]
    other = [[3.0, 0.0, -1.0, -1.0], [6.0, 3.0, 1.0, 1.0]]

    def verdict(seed, outcome, start=box):
        return dict(seed=seed, start=0, target=1, outcome=outcome, start_box=start,
                    target_box=other)

    result = SimpleNamespace(seeds=[5, 7], host_info=[
        None, {"verdicts": [verdict(1, "no_reach"), verdict(1, "split")]},
        {"verdicts": []}, {"verdicts": [verdict(0, "split", other), verdict(1, "split")]}])
    log = split_log(result)
    assert [[e["epoch"] for e in seed] for seed in log] == [[3], [1, 3]]
    assert log[0][0]["start"] == other and log[1][0]["target"] == other
    counts = analysis_counts(result)
    assert [(e["outcome"], e["count"], e["first_epoch"]) for e in counts[1]] == [
        ("no_reach", 1, 1), ("split", 2, 1)]
    assert counts[0] == [dict(start=[3.0, 6.0, 0.0, 3.0], target=[3.0, 6.0, 0.0, 3.0],
                              outcome="split", count=1, first_epoch=3)]


def test_cut_table_groups_seeds_by_the_goals_their_final_partition_cuts():
    from experiments.mazes import cut_table, goal_cuts

    whole = [[[0, 0, -1, -1], [1, 0, -1, -1]], [[1, 3, 1, 1], [3, 3, 1, 1]]]
    right_y = [[[0, 0, -1, -1], [1, 0, -1, -1], [1, 1.5, -1, -1]],
               [[1, 3, 1, 1], [3, 1.5, 1, 1], [3, 3, 1, 1]]]
    left_v = [[[0, 0, -1, -1], [0, 0, 0, -1], [1, 0, -1, -1]],
              [[1, 3, 0, 1], [1, 3, 1, 1], [3, 3, 1, 1]]]
    assert [goal_cuts("u_maze", *p) for p in (whole, right_y, left_v)] == ["- -", "- y", "v -"]

    def run(greedy, partitions=None, **config):
        train = [1.0 - g for g in greedy]  # distinct from greedy, so a mix-up shows
        return {"summary": {"per_seed": {"greedy_last10": greedy, "train_last30k": train}},
                "config": config, "final_partitions": partitions}

    runs = {"u_maze": {
        "gara_no_refinement": run([0.5, 0.6, 0.7]),
        "gara": run([0.9, 0.4, 0.7], [right_y, right_y, whole]),
        "gara+one_cut": run([0.1, 0.2, 0.3], [whole, left_v, whole]),
        "gara@seeds20-39": run([1.0, 1.0, 1.0], [whole] * 3),  # another block: left out
        "gara+boxes": run([1.0, 1.0, 1.0], [whole] * 3, initial_boxes=[[0]]),  # left out
    }}
    rows = [r for r in cut_table(runs, "u_maze").splitlines() if r.startswith("| `")]
    # "- -": gara seed 2 and gara+one_cut seeds 0, 2: (0.7 + 0.1 + 0.3) / 3 against
    # (0.7 + 0.5 + 0.7) / 3; training is 1 minus each.
    assert rows == ["| `- -` | 3 | 0.37 / 0.63 / -0.27 | 0.63 / 0.37 / +0.27 |",
                    "| `- y` | 2 | 0.65 / 0.55 / +0.10 | 0.35 / 0.45 / -0.10 |",
                    "| `v -` | 1 | 0.20 / 0.60 / -0.40 | 0.80 / 0.40 / +0.40 |"]
