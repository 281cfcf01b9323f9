"""GARA's host step between epochs: when a pair is analysed, how, and what a split changes.

It runs after every epoch (``cadence="epoch"``) or, for the seeds whose episode just ended,
after every episode (``cadence="episode"``, the reference; the driver stops each seed at its
episode's end, see :func:`gara_jax.train.train_epochs`); "the last epoch" below is then that
episode. Read top to bottom, for all seeds at once (the states are batched over seeds):

1. **Trigger** (SPEC.md section 3.5). A pair ``(G_s, G_d)``, ``s != d``, explored during the
   last epoch, not known reachable, not blocked (a split that did not fit), not marked
   unreachable when ``skip_unreachable``, with at least ``min_steps`` of experience, and
   with ``keep_start_goal`` no ``G_s`` that holds a start state; with
   ``exit_analysis`` also ``(G_e, G_e)``, ``G_e`` the goal holding the last exit state, whose
   analysis measures coverage against a box around that state (:func:`exit_box`). With
   ``pair_counts="memory"`` the experience is derived from the high-level memory (the summed
   ``length`` of the pair's rows, the goals located from the stored states and target
   bounds), so it stays right after splits without bookkeeping; with ``"cumulative"`` it is
   the reference's counter keyed by goal index (``GaraState.pair_count``, counted in the
   jitted steps).
2. **Forward model.** ``forward_model="per_job"``: a fresh model per analysis job, all jobs
   trained in one batched call until their loss is stable; unstable jobs are skipped.
   ``"shared"`` (the reference): every triggered pair updates its seed's shared model once per
   episode of the epoch in which it was chosen (one gradient step on at most 32 of its rows,
   then an MSE record on a fresh sample); a pair with at least ``shared_min_records`` records
   whose latest MSE is less than ``forward.stable_decrease`` above the previous one is
   analysed.
3. **Analysis**: one batched :func:`gara_jax.reach.refine_many` over every job, at most
   ``max_jobs_per_seed`` per seed, taken by decreasing experience and skipping any that
   touches a goal being split in the same step.
4. **Splits** on host copies of each seed's padded partition, Q-table, planner graph and marks
   (:func:`apply_split`), the epsilon boost, then everything written back with the layout it
   came with (seed-sharded over the driver's devices, :mod:`gara_jax.train`); with
   ``relabel_replay`` the low-level replay of every seed whose partition grew (or, with
   ``relabel_after="update"``, whose verdicts changed) gets its hindsight copies
   (:func:`gara_jax.agents.dqn.append_relabelled`), and with ``relabel_counts`` the memory's
   rows change the cumulative counts.

The host pulls the small per-pair arrays of every seed (partition, marks, experience counts)
and, of the large ones (the high-level memory), only the rows of the seeds that have a
triggered pair; everything batched over seeds that stays on the devices (memory lookups, the
shared model's updates, relabelling, replanning) runs where the seeds live.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from gara_jax.agents import forward_model as fm
from gara_jax.agents import high_level as hl
from gara_jax.networks import mlp_layers
from gara_jax.sharding import SeedJit


def make_host_update(config, locate, exit_goals, dqn, forward, start_obs=None):
    """``host_update(states, epoch) -> (states, info)`` for a :class:`GaraConfig`.

    ``locate``/``exit_goals`` are the agent's goal lookups, ``dqn`` its low-level learner and
    ``forward`` the :class:`~gara_jax.agents.forward_model.ForwardModel`; ``start_obs``
    (``[N, D]``, with ``keep_start_goal``) the start states whose goals are never ``G_s``.
    ``info`` counts what happened (``triggered``, ``stable``, ``analysed``, ``splits``,
    ``reaches``, ``no_reach``, ``capacity_skips``, ``fit_updates``, ``start_skips``; of them
    ``exit_analysed``, ``exit_splits`` for the ``exit_analysis`` pairs), holds
    ``changed [n_seeds]`` (partition grew), ``updated [n_seeds]`` (a split, or a whole ``G_s``
    found reaching), ``verdicts`` (one dict per analysis: ``seed``, the seed's index in the
    batch; ``start``, ``target``, the goal indices; ``outcome``, :func:`apply_split`'s; and
    ``start_box``, ``target_box``, ``[lo, hi]`` before the step's splits) and the time spent
    (``fit_s``, ``refine_s``, ``host_s``).
    """
    from gara_jax import boxes
    from gara_jax import partition as part
    from gara_jax import reach

    G = config.max_goals
    dim = 4
    shared = config.forward_model == "shared"
    cumulative = config.pair_counts == "cumulative"
    aliased = config.q_rows_after_split == "aliased"

    @SeedJit
    @jax.vmap
    def memory_goals(state, since):
        """Goal indices of every memory row and the per-pair experience (device side); a pair
        is recent if a row of it was stored after env step ``since``."""
        mem, partition = state.memory, state.partition
        start = locate(partition, mem.start)
        target = fm.match_boxes(mem.target_lo, mem.target_hi, partition.lo, partition.hi,
                                partition.count)
        steps, recent = fm.pair_experience(start, target, mem, since, G)
        return start, target, steps, recent

    @SeedJit
    @jax.vmap
    def pair_ranges(memory, start, target):
        return fm.pair_start_ranges(start, target, memory, G)

    @SeedJit
    @jax.vmap
    def exit_pairs(state):
        """``[G]``: the goal holding the last exit state (``exit_analysis``), if one is known."""
        return exit_goals(state.high, state.partition)

    @SeedJit
    @jax.vmap
    def shared_updates(forward_state, memory, rows, seg_start, seg_len, live, key_data):
        x = model_inputs(config, memory.start, memory.target_lo, memory.target_hi, jnp)
        keys = jax.random.wrap_key_data(key_data)
        return forward.shared_updates(forward_state.params, forward_state.opt_state, x,
                                      memory.end, rows, seg_start, seg_len, live, keys)

    @SeedJit
    @jax.vmap
    def relabel(dqn_state, partition, where):
        return dqn.append_relabelled(
            dqn_state, lambda t: relabel_to_reached_goal(t, partition, dim), where)

    @SeedJit
    @jax.vmap
    def relabel_counts(pair_count, memory, old_partition, new_partition, where):
        """The memory relabel's count changes (``relabel_counts``; SPEC.md section 3.9.2)."""
        rows = (jnp.arange(memory.capacity + 1) < memory.size) & memory.data
        old = locate(old_partition, memory.start)
        new = locate(new_partition, memory.start)
        # Targets by index: a piece that keeps an index inherits the rows towards it.
        target = fm.match_boxes(memory.target_lo, memory.target_hi, old_partition.lo,
                                old_partition.hi, old_partition.count)
        ok = rows & (target >= 0) & where
        flat = lambda start: jnp.where(ok, start * G + jnp.maximum(target, 0), 0)
        count = pair_count.reshape(-1).at[flat(new)].add(ok.astype(jnp.int32))
        if config.relabel_counts == "move":
            count = count.at[flat(old)].add(-ok.astype(jnp.int32))
        return count.reshape(G, G)

    @SeedJit
    @jax.vmap
    def replan(state, where):
        """Exact planner distances on the refined partitions (of the seeds ``where``)."""
        high = state.high
        dist = hl.shortest_distances(high.succeeded, exit_goals(high, state.partition),
                                     state.partition.count)
        return high.replace(dist=jnp.where(where, dist, high.dist))

    def seed_keys(host_key, counter, salt):
        keys = jax.random.wrap_key_data(jnp.asarray(host_key))
        counter = jnp.broadcast_to(jnp.asarray(counter, jnp.uint32), keys.shape)
        return jax.vmap(lambda k, c: jax.random.fold_in(jax.random.fold_in(k, c), salt))(
            keys, counter)

    def host_update(states, epoch: int, *, only=None, since=None, key_index=None):
        """The host step after epoch ``epoch`` (``cadence="epoch"``: what the last
        ``steps_per_epoch`` steps explored), or, with ``only`` (``bool [n_seeds]``), after
        the episode each seed ``only`` just finished (``cadence="episode"``): ``since``
        (``[n_seeds]``) the env step at which that episode started (rows stored after it are
        the episode's), ``key_index`` (``[n_seeds]``) the episode's index, which seeds the
        step's random keys instead of the epoch. The other seeds are left exactly as they are.
        """
        t0 = time.perf_counter()
        n_seeds = len(states.host_key)
        if since is None:
            since = np.asarray(jax.device_get(states.env_steps)) - config.steps_per_epoch
        since = np.asarray(since, np.int64).reshape(n_seeds)
        counter = epoch if key_index is None else np.asarray(key_index).reshape(n_seeds)
        start_goal, target_goal, steps, recent = memory_goals(
            states, put_like(since, states.env_steps))
        if cumulative:
            steps = states.pair_count  # the reference's counts (SPEC.md 3.9.3)
        steps, recent = jax.device_get((steps, recent))
        host = jax.device_get(dict(
            count=states.partition.count, lo=states.partition.lo, hi=states.partition.hi,
            rank=states.partition.rank,
            reachable=states.reachable, unreachable=states.unreachable, blocked=states.blocked,
            host_key=states.host_key, records=states.forward.records,
            mse_last=states.forward.mse_last, mse_prev=states.forward.mse_prev))
        info = dict(epoch=epoch, triggered=0, stable=0, analysed=0, splits=0, reaches=0,
                    no_reach=0, capacity_skips=0, fit_updates=0, start_skips=0,
                    exit_analysed=0, exit_splits=0, verdicts=[],
                    changed=np.zeros(n_seeds, bool), updated=np.zeros(n_seeds, bool),
                    fit_s=0.0, refine_s=0.0)

        # 1. The trigger.
        ok = recent & (steps >= config.min_steps) & ~host["reachable"] & ~host["blocked"]
        if config.skip_unreachable:
            ok &= ~host["unreachable"]
        exit_goal = np.zeros((n_seeds, G), bool)
        if config.exit_analysis:
            # The one pair s == d: options towards the goal holding the exit, from inside it.
            exit_goal = np.asarray(jax.device_get(exit_pairs(states)), bool)
        ok[:, np.arange(G), np.arange(G)] &= exit_goal
        if only is not None:
            ok &= np.asarray(only, bool).reshape(n_seeds)[:, None, None]
        live_goals = np.arange(G)[None, :] < host["count"][:, None]
        ok &= live_goals[:, :, None] & live_goals[:, None, :]
        if start_obs is not None:
            # keep_start_goal: a goal holding a start state is never G_s (closed boxes).
            holds = np.asarray(boxes.contains(host["lo"][:, :, None], host["hi"][:, :, None],
                                              np.asarray(start_obs)[None, None])).any(-1)
            info["start_skips"] = int((ok & holds[:, :, None]).sum())
            ok &= ~holds[:, :, None]
        info["triggered"] = int(ok.sum())

        # 2. Forward models; the jobs whose model is ready for analysis, and its parameters.
        t_fit = time.perf_counter()
        if shared:
            ready, new_forward, info["fit_updates"] = _shared_step(
                config, states, host, ok, shared_updates, start_goal, target_goal,
                seed_keys(host["host_key"], counter, 1), since)
            states = states.replace(forward=new_forward)
            jobs = _choose_jobs(config, ready, steps)
            seeds_idx = np.asarray([i for i, _, _ in jobs], int)
            job_params = jax.tree.map(lambda p: np.asarray(p)[seeds_idx],
                                      jax.device_get(new_forward.params))
        else:
            jobs = _choose_jobs(config, ok, steps)
            if jobs:
                stable, fit_params = _fit_per_job(config, forward, states, jobs, start_goal,
                                                  target_goal, host["host_key"], counter)
                keep = np.flatnonzero(stable)
                jobs = [jobs[j] for j in keep]
                job_params = jax.tree.map(lambda p: p[keep], fit_params)
        info["fit_s"] = time.perf_counter() - t_fit
        info["stable"] = len(jobs)
        if not jobs:
            info["host_s"] = time.perf_counter() - t0
            return states, info

        # 3. One batched reachability analysis for every job.
        t_ref = time.perf_counter()
        lo, hi = host["lo"], host["hi"]
        cover_lo = np.stack([lo[i][d] for i, _, d in jobs])
        cover_hi = np.stack([hi[i][d] for i, _, d in jobs])
        exit_jobs = [j for j, (_, s, d) in enumerate(jobs) if s == d]
        if exit_jobs:
            exit_state = np.asarray(jax.device_get(states.high.exit_state))
            for j in exit_jobs:
                i, e, _ = jobs[j]
                cover_lo[j], cover_hi[j] = exit_box(lo[i][e], hi[i][e], exit_state[i],
                                                    config.exit_radius, config.split_dims)
        start_lo = np.stack([lo[i][s] for i, s, _ in jobs])
        start_hi = np.stack([hi[i][s] for i, s, _ in jobs])
        input_lo = input_hi = None
        if config.model_inputs == "split_dims":
            # The dimensions the model does not see are 0 in its inputs, so in its bounds too.
            unseen = ~model_mask(config, dim)
            input_lo, input_hi = np.where(unseen, 0.0, start_lo), np.where(unseen, 0.0, start_hi)
        if config.input_range == "data":
            input_lo, input_hi = _data_input_boxes(
                config, jax.device_get(pair_ranges(states.memory, start_goal, target_goal)),
                jobs, lo, hi)
        reach_lo = reach_hi = None
        if config.reach_clip == "space":
            # The space the partition tiles: no true successor state lies outside it.
            n_live = host["count"]
            reach_lo = np.stack([lo[i][:n_live[i]].min(0) for i, _, _ in jobs])
            reach_hi = np.stack([hi[i][:n_live[i]].max(0) for i, _, _ in jobs])
        results = reach.refine_many(
            mlp_layers(job_params), start_lo, start_hi,
            np.stack([lo[i][d] for i, _, d in jobs]), np.stack([hi[i][d] for i, _, d in jobs]),
            cover_lo=cover_lo, cover_hi=cover_hi, input_lo=input_lo, input_hi=input_hi,
            tau1=config.tau1, tau2=config.tau2, min_volume_ratio=config.min_volume_ratio,
            method=config.refine_method, small_box_c1=config.small_box_c1,
            coverage=config.coverage, target_margin=config.target_margin,
            split_dims=config.split_dims, merge=config.merge, split_rule=config.split_rule,
            reach_lo=reach_lo, reach_hi=reach_hi)
        info["refine_s"] = time.perf_counter() - t_ref

        # 4. Apply the verdicts seed by seed on host copies, then write everything back.
        arrays = jax.device_get(dict(q=states.high.q, succeeded=states.high.succeeded,
                                     stale=states.option.stale, epsilon=states.high.epsilon,
                                     alias=states.high.alias, pair_count=states.pair_count))
        # Arrays indexed by goal that the splits rewrite (alias groups, counts: if kept).
        per_goal = ["q", "succeeded", "reachable", "unreachable", "blocked", "records"]
        per_goal += ["alias"] if aliased else []
        per_goal += ["pair_count"] if cumulative else []
        ranked = host["rank"] is not None  # piece_order="parent"
        new = {k: np.array(v) for k, v in dict(
            lo=lo, hi=hi, count=host["count"], q=arrays["q"], succeeded=arrays["succeeded"],
            reachable=host["reachable"], unreachable=host["unreachable"],
            blocked=host["blocked"], stale=arrays["stale"], epsilon=arrays["epsilon"],
            records=jax.device_get(states.forward.records), alias=arrays["alias"],
            pair_count=arrays["pair_count"]).items() if v is not None}
        if ranked:
            new["rank"] = np.array(host["rank"])
        seeds = {}
        for (i, s_idx, d_idx), result in zip(jobs, results, strict=True):
            if i not in seeds:
                n = host["count"][i]
                seeds[i] = dict(
                    partition=part.Partition.create(lo[i][:n], hi[i][:n], G,
                                                    rank=host["rank"][i] if ranked else None),
                    **{name: new[name][i].copy() for name in per_goal})
            outcome = apply_split(seeds[i], s_idx, d_idx, result, config.q_columns,
                                  config.q_rows_after_split, config.records_after_split)
            # What was analysed, with the boxes as they were before any split of this step.
            info["verdicts"].append(dict(
                seed=int(i), start=int(s_idx), target=int(d_idx), outcome=outcome,
                start_box=[lo[i][s_idx].tolist(), hi[i][s_idx].tolist()],
                target_box=[lo[i][d_idx].tolist(), hi[i][d_idx].tolist()]))
            info["analysed"] += 1
            info["splits"] += outcome == "split"
            info["reaches"] += outcome == "reaches"
            info["no_reach"] += outcome == "no_reach"
            info["capacity_skips"] += outcome == "capacity"
            info["exit_analysed"] += s_idx == d_idx
            info["exit_splits"] += s_idx == d_idx and outcome == "split"
            if outcome == "split":
                info["changed"][i] = True
                new["epsilon"][i] = min(1.0, new["epsilon"][i] * config.split_epsilon_boost)
            if outcome in ("split", "reaches"):
                info["updated"][i] = True
        for i, seed in seeds.items():
            p = seed["partition"]
            new["lo"][i], new["hi"][i], new["count"][i] = p.lo, p.hi, p.count
            if ranked:
                new["rank"][i] = p.rank
            for name in per_goal:
                new[name][i] = seed[name]
            new["stale"][i] |= info["changed"][i]
        old_partition = states.partition
        partition = states.partition.replace(
            lo=put_like(new["lo"], states.partition.lo),
            hi=put_like(new["hi"], states.partition.hi),
            count=put_like(new["count"], states.partition.count),
            rank=put_like(new["rank"], states.partition.rank) if ranked else None)
        high = states.high.replace(q=put_like(new["q"], states.high.q),
                                   succeeded=put_like(new["succeeded"], states.high.succeeded),
                                   epsilon=put_like(new["epsilon"], states.high.epsilon))
        if aliased:
            high = high.replace(alias=put_like(new["alias"], states.high.alias))
        if cumulative:
            states = states.replace(pair_count=put_like(new["pair_count"], states.pair_count))
        states = states.replace(
            partition=partition, high=high,
            reachable=put_like(new["reachable"], states.reachable),
            unreachable=put_like(new["unreachable"], states.unreachable),
            blocked=put_like(new["blocked"], states.blocked),
            option=states.option.replace(stale=put_like(new["stale"], states.option.stale)),
            forward=states.forward.replace(records=put_like(new["records"],
                                                            states.forward.records)))
        # The relabels run after a split, or (relabel_after="update") after any update.
        relabelled = info["updated"] if config.relabel_after == "update" else info["changed"]
        if config.relabel_replay and relabelled.any():
            states = states.replace(dqn=relabel(states.dqn, states.partition, relabelled))
        if config.relabel_counts != "none" and relabelled.any():
            states = states.replace(pair_count=relabel_counts(
                states.pair_count, states.memory, old_partition, states.partition, relabelled))
        if config.planning:
            # After an epoch: every seed. After episodes: the seeds analysed (so that no seed's
            # planner depends on what happened to the others).
            where = np.ones(n_seeds, bool) if only is None else np.isin(
                np.arange(n_seeds), list(seeds))
            states = states.replace(high=replan(states, put_like(where, states.option.stale)))
        info["host_s"] = time.perf_counter() - t0
        return states, info

    return host_update


def exit_box(goal_lo, goal_hi, exit_state, radius: float, dims=None):
    """The box an exit analysis measures coverage against (GARA's ``exit_analysis``).

    The goal ``goal_lo/goal_hi`` narrowed, along ``dims`` (``None``: every dimension), to
    ``radius`` times its width on each side of ``exit_state``; the other dimensions keep the
    goal's range.

    Example:
        >>> import numpy as np
        >>> lo, hi = exit_box(np.array([3., 0, -1, -1]), np.array([6., 3, 1, 1]),
        ...                   np.array([6., 3, 0.2, 0.5]), 0.25, dims=(0, 1))
        >>> lo.tolist(), hi.tolist()
        ([5.25, 2.25, -1.0, -1.0], [6.0, 3.0, 1.0, 1.0])
    """
    goal_lo, goal_hi = np.asarray(goal_lo, float), np.asarray(goal_hi, float)
    exit_state = np.asarray(exit_state, float)
    narrow = np.zeros(goal_lo.shape, bool)
    narrow[list(range(len(goal_lo))) if dims is None else list(dims)] = True
    half = radius * (goal_hi - goal_lo)
    lo = np.where(narrow, np.clip(exit_state - half, goal_lo, goal_hi), goal_lo)
    hi = np.where(narrow, np.clip(exit_state + half, goal_lo, goal_hi), goal_hi)
    return lo, hi


def split_mask(split_dims, dim: int) -> np.ndarray:
    """``bool [dim]``: the dimensions in ``split_dims`` (every one for ``None``)."""
    mask = np.ones(dim, bool)
    if split_dims is not None:
        mask[:] = False
        mask[list(split_dims)] = True
    return mask


def model_mask(config, dim: int) -> np.ndarray:
    """``bool [dim]``: the start-state dimensions GARA's forward model sees
    (``model_inputs``)."""
    if config.model_inputs == "split_dims":
        return split_mask(config.split_dims, dim)
    return np.ones(dim, bool)


def model_inputs(config, start, target_lo, target_hi, xp=np):
    """The forward model's inputs ``s || G.lo || G.hi`` (``[..., 3 D]``), with the start
    dimensions the model does not see (``model_inputs="split_dims"``) set to 0.

    Example:
        >>> from gara_jax.algorithms import GaraConfig
        >>> s, g = np.array([[1.0, 2.0, 0.5, -0.5]]), np.zeros((1, 4))
        >>> model_inputs(GaraConfig(model_inputs="split_dims"), s, g, g)[0, :4]
        array([1., 2., 0., 0.])
    """
    if config.model_inputs != "state":
        start = xp.where(model_mask(config, start.shape[-1]), start, 0.0)
    return xp.concatenate([start, target_lo, target_hi], axis=-1)


def _data_input_boxes(config, ranges, jobs, lo, hi):
    """``input_range="data"``: each job's input box, ``G_s`` narrowed along the dimensions not
    in ``split_dims`` to the range of its pair's data rows (``G_s`` itself where the pair has
    no data row, e.g. only count rows)."""
    r_lo, r_hi = ranges
    # split_dims=None: every dimension is split, none narrowed.
    narrow = ~split_mask(config.split_dims, lo.shape[-1])
    in_lo = np.stack([lo[i][s] for i, s, _ in jobs]).astype(float)
    in_hi = np.stack([hi[i][s] for i, s, _ in jobs]).astype(float)
    for j, (i, s, d) in enumerate(jobs):
        d_lo, d_hi = r_lo[i, s, d], r_hi[i, s, d]
        if np.all(d_lo <= d_hi):
            in_lo[j] = np.where(narrow, np.clip(d_lo, in_lo[j], in_hi[j]), in_lo[j])
            in_hi[j] = np.where(narrow, np.clip(d_hi, in_lo[j], in_hi[j]), in_hi[j])
    return in_lo, in_hi


def put_like(value, like):
    """Host ``value`` as a device array with ``like``'s dtype and layout (sharding).

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> out = put_like(np.array([1.5, 2.5]), jnp.zeros(2, jnp.int32))
        >>> out.dtype, out.sharding == jnp.zeros(2).sharding
        (dtype('int32'), True)
    """
    return jax.device_put(np.asarray(value, like.dtype), like.sharding)


def relabel_to_reached_goal(transitions, partition, dim: int = 4):
    """Low-level transitions ``s ‖ goal -> s' ‖ goal`` relabelled with the goal now holding
    ``s'`` (first-box rule) and reward 1: the reference's hindsight copies after a split.

    Example:
        >>> import jax.numpy as jnp
        >>> from gara_jax.agents.dqn import Transition
        >>> from gara_jax.partition import Partition
        >>> p = Partition.create([[0.0], [1.0]], [[1.0], [2.0]], max_goals=2)
        >>> t = Transition(jnp.zeros((1, 3)), jnp.zeros(1, int), jnp.zeros(1),
        ...                jnp.array([[1.5, 0.0, 1.0]]), jnp.zeros(1, bool))
        >>> r = relabel_to_reached_goal(t, p, dim=1)
        >>> r.obs.tolist(), r.next_obs.tolist(), r.reward.tolist()
        ([[0.0, 1.0, 2.0]], [[1.5, 1.0, 2.0]], [1.0])
    """
    from gara_jax import partition as part

    next_s = transitions.next_obs[:, :dim]
    goal = jnp.maximum(part.locate(partition, next_s), 0)
    goal_in = jnp.concatenate([partition.lo[goal], partition.hi[goal]], axis=-1)
    return transitions._replace(
        obs=jnp.concatenate([transitions.obs[:, :dim], goal_in], axis=-1),
        next_obs=jnp.concatenate([next_s, goal_in], axis=-1),
        reward=jnp.ones_like(transitions.reward))


def _choose_jobs(config, candidates, steps):
    """``[(seed, s, d)]``: per seed, candidate pairs by decreasing experience, at most
    ``max_jobs_per_seed``, none touching a goal that another job of the seed splits."""
    jobs = []
    for i in range(len(candidates)):
        pairs = sorted(zip(*np.nonzero(candidates[i]), strict=True),
                       key=lambda p, i=i: -steps[i][p])
        splitting, touched, n = set(), set(), 0
        for s_idx, d_idx in pairs:
            if n >= config.max_jobs_per_seed:
                break
            if s_idx in touched or s_idx in splitting or d_idx in splitting:
                continue
            jobs.append((i, int(s_idx), int(d_idx)))
            splitting.add(s_idx)
            touched.update((s_idx, d_idx))
            n += 1
    return jobs


def _seed_rows(tree, seeds):
    """The rows ``seeds`` of every leaf of ``tree`` (arrays ``[S, ...]``), as NumPy.

    Only those rows leave the devices. The index is padded to a power of two (repeating its
    last seed), so that the device gather compiles for a few sizes, not for every count of
    seeds; the padding is dropped on the host.
    """
    seeds = np.asarray(seeds, int)
    n = len(seeds)
    padded = np.concatenate([seeds, np.full(max(1, 1 << (n - 1).bit_length()) - n, seeds[-1])])
    return jax.tree.map(lambda a: np.asarray(a)[:n],
                        jax.device_get(_take_rows(tree, jnp.asarray(padded))))


_take_rows = jax.jit(lambda tree, take: jax.tree.map(lambda a: a[take], tree))


def _fit_per_job(config, forward, states, jobs, start_goal, target_goal, host_key, epoch):
    """Fresh forward models for ``jobs``, trained in one batched call: ``(stable, params)``.

    ``epoch``: the epoch, or per seed the episode index, that seeds the jobs' keys."""
    G = config.max_goals
    # Only the memory rows of the seeds with a job leave the devices.
    job_seeds = sorted({i for i, _, _ in jobs})
    row_of = {seed: r for r, seed in enumerate(job_seeds)}
    mem, start_goal, target_goal = _seed_rows((states.memory, start_goal, target_goal),
                                              job_seeds)
    datasets = []
    for i, s_idx, d_idx in jobs:
        r = row_of[i]
        rows = np.flatnonzero((np.arange(len(start_goal[r])) < mem.size[r]) & mem.data[r]
                              & (start_goal[r] == s_idx) & (target_goal[r] == d_idx))
        x = model_inputs(config, mem.start[r][rows], mem.target_lo[r][rows],
                         mem.target_hi[r][rows], np)
        datasets.append((x, mem.end[r][rows]))
    n_jobs = len(jobs)
    # Jobs padded to a power of two (at least 8) and rows to 1024 * 4^i (at most the memory
    # capacity): only a few shapes ever get compiled, whatever the jobs and their data sizes.
    padded_jobs = max(8, 1 << int(np.ceil(np.log2(n_jobs))))
    datasets += [(np.zeros((0, 12), np.float32), np.zeros((0, 4), np.float32))] * (
        padded_jobs - n_jobs)
    x, y, mask = fm.pad_jobs(datasets, config.forward.batch_size, min_rows=1024,
                             max_rows=config.memory_capacity)
    # Job keys depend only on the job's own seed, the epoch (episode) and the pair.
    keys = jax.random.wrap_key_data(jnp.asarray(host_key))
    counter = lambda i: epoch if np.ndim(epoch) == 0 else int(epoch[i])  # noqa: E731
    job_keys = [jax.random.fold_in(jax.random.fold_in(keys[i], counter(i)), s_idx * G + d_idx)
                for i, s_idx, d_idx in jobs]
    job_keys = jnp.stack(job_keys + [job_keys[0]] * (padded_jobs - n_jobs))
    k_init = jax.vmap(lambda k: jax.random.fold_in(k, 0))(job_keys)
    k_fit = jax.vmap(lambda k: jax.random.fold_in(k, 1))(job_keys)
    fit = forward.fit(forward.init(k_init), x, y, mask, k_fit)
    return np.asarray(fit.stable)[:n_jobs], jax.tree.map(lambda p: p[:n_jobs], fit.params)


def _shared_step(config, states, host, ok, shared_updates, start_goal, target_goal, keys,
                 since):
    """The reference's incremental fits: ``(ready [S, G, G], new SharedForward, n_updates)``.

    Every triggered pair gets one update per episode since env step ``since [S]`` (the last
    epoch, or the episode just finished) in which it was chosen
    (its option-start rows carry the episode index), in episode order; each update draws its
    rows as ``forward.shared_sample`` says (uniformly with replacement, or, as the reference,
    at most ``batch_size`` distinct rows). A pair is ready when it has
    ``shared_min_records`` records and its latest MSE is less than ``stable_decrease`` above
    the previous one.
    """
    G = config.max_goals
    n_seeds = len(ok)
    # Only the seeds with a triggered pair get updates; only their memory rows leave the devices.
    active = np.flatnonzero(ok.reshape(n_seeds, -1).any(axis=1))
    if len(active) == 0:
        return np.zeros_like(ok), states.forward, 0
    mem, start_np, target_np = _seed_rows(
        (states.memory.replace(start=None, end=None, target_lo=None, target_hi=None,
                               reward=None), start_goal, target_goal), active)
    since = np.asarray(since)[active]
    updates, pair_ids = [], []
    for r, i in enumerate(active):
        filled = (np.arange(len(start_np[r])) < mem.size[r]) & (start_np[r] >= 0) & (
            target_np[r] >= 0)
        pair = np.where(filled, start_np[r].astype(np.int64) * G + target_np[r], -1)
        pair_ids.append(pair)
        # Option choices: the count-only option-start rows of the window memory, else options.
        choices = ~mem.data[r] if config.memory == "windows" else True
        rows = np.flatnonzero(filled & choices & (mem.step[r] > since[r]))
        chosen = rows[ok[i].reshape(-1)[pair[rows]]]
        # Unique (episode, pair) in episode order: one update each.
        key = np.unique(mem.episode[r][chosen].astype(np.int64) * G * G + pair[chosen])
        updates.append(key % (G * G))
    n_max = max(len(u) for u in updates)
    if n_max == 0:
        return np.zeros_like(ok), states.forward, 0
    width = max(8, 1 << int(np.ceil(np.log2(n_max))))
    capacity = len(start_np[0])
    rows = np.zeros((n_seeds, capacity), np.int32)
    seg_start = np.zeros((n_seeds, width), np.int32)
    seg_len = np.zeros((n_seeds, width), np.int32)
    live = np.zeros((n_seeds, width), bool)
    for r, (i, u) in enumerate(zip(active, updates, strict=True)):
        rows[i], seg_start[i, : len(u)], seg_len[i, : len(u)] = fm.pair_segments(
            pair_ids[r], mem.data[r] & (pair_ids[r] >= 0), u)
        live[i, : len(u)] = True
    update_keys = jax.random.key_data(jax.vmap(lambda k: jax.random.split(k, width))(keys))
    params, opt_state, mse = shared_updates(states.forward, states.memory, rows, seg_start,
                                            seg_len, live, update_keys)
    mse = np.asarray(jax.device_get(mse))
    records, last, prev = (np.array(host[name]) for name in ("records", "mse_last", "mse_prev"))
    for i, u in zip(active, updates, strict=True):
        for j, flat in enumerate(u):
            s_idx, d_idx = divmod(int(flat), G)
            prev[i, s_idx, d_idx] = last[i, s_idx, d_idx]
            last[i, s_idx, d_idx] = mse[i, j]
            records[i, s_idx, d_idx] += 1
    ready = ok & (records >= config.shared_min_records) & (
        last - prev < config.forward.stable_decrease)
    new_forward = states.forward.replace(
        params=params, opt_state=opt_state, records=put_like(records, states.forward.records),
        mse_last=put_like(last, states.forward.mse_last),
        mse_prev=put_like(prev, states.forward.mse_prev))
    return ready, new_forward, int(live.sum())


def apply_split(seed: dict, s: int, d: int, result, q_columns: str = "copy",
                q_rows: str = "copied", records: str = "cleared") -> str:
    """Apply one analysis of the pair ``(G_s, G_d)`` to a seed's host-side arrays (in place).

    ``G_s`` is replaced by the reaching boxes then the non-reaching ones (the first keeps index
    ``s``, the others are appended). What indexes goals is updated as follows:

    - Q-table: the rows of every piece are copies of ``G_s``'s; the columns follow
      ``q_columns`` (``"copy"``: every piece gets ``G_s``'s column, and entries between pieces
      ``G_s``'s self-value; ``"reference"``: piece ``s`` keeps its column, the others get 0;
      ``"zero"``: all 0); then ``Q[piece, d] = 0`` for the non-reaching pieces (as the
      reference does). ``q_rows`` (GARA's ``q_rows_after_split``): ``"copied"`` zeroes only the
      non-reaching pieces' entries; ``"aliased_at_split"`` zeroes ``Q[g, d]`` for every piece
      ``g`` once any piece does not reach (the rows are one object in the reference);
      ``"aliased"`` also puts the pieces into ``G_s``'s alias group (``seed["alias"]``) and
      zeroes the whole group's entries; ``"kept"`` zeroes nothing.
    - Planner graph: rows and columns copied; then the edge ``piece -> d`` is set for reaching
      pieces and removed for non-reaching ones.
    - Reachability marks: a piece's *row* (the piece as a start) inherits ``G_s``'s verdicts
      towards other goals (a subset of a box that reaches, or misses, a goal does so too);
      its *column* (the piece as a target) is cleared, since the old verdicts were about a
      larger target. Then reaching pieces are marked reachable towards ``G_d`` and the others
      unreachable.
    - Shared forward-model records (``seed["records"]``, if present): cleared for every pair
      that involves a piece (``records="cleared"``), or only for the appended pieces, index
      ``s`` keeping its records (``records="kept"``, the reference's records keyed by index).
    - Cumulative pair counts (``seed["pair_count"]``, if present): index ``s`` keeps them, the
      appended pieces' rows and columns start from 0.

    ``s == d`` is an exit analysis (GARA's ``exit_analysis``): the verdicts are about the exit
    box, so after the split only ``(s, s)`` is marked reachable (``s`` is the first reaching
    piece), and the other pieces keep their copied Q rows, planner edges and marks towards
    ``s``, with no zeroing.

    An analysis whose boxes merge back into ``G_s`` changes no box: if all of ``G_s`` reaches,
    the pair is marked reachable; if none of it does, nothing is marked (as in the reference,
    which only marks the non-reaching pieces of a split), so the pair is analysed again later
    with a better-trained low level. A split that does not fit in the capacity is skipped and
    the pair marked ``blocked``. Returns ``"split"``, ``"reaches"``, ``"no_reach"`` or
    ``"capacity"``.
    """
    from gara_jax import partition as part

    reach_lo = np.asarray(result.reaching_lo).reshape(-1, 4)
    reach_hi = np.asarray(result.reaching_hi).reshape(-1, 4)
    miss_lo = np.asarray(result.nonreaching_lo).reshape(-1, 4)
    miss_hi = np.asarray(result.nonreaching_hi).reshape(-1, 4)
    n_reach = len(reach_lo)
    boxes_lo = np.concatenate([reach_lo, miss_lo])
    boxes_hi = np.concatenate([reach_hi, miss_hi])
    if len(boxes_lo) <= 1:
        if n_reach == 0:
            # Nothing of G_s reaches G_d (yet): as in the reference, the pair stays open and is
            # analysed again once explored anew, with a better low-level policy and more data.
            return "no_reach"
        seed["reachable"][s, d] = True
        return "reaches"
    if not part.can_fit(seed["partition"], len(boxes_lo) - 1):
        seed["blocked"][s, d] = True
        return "capacity"
    seed["partition"], pieces = part.replace_box(seed["partition"], s, boxes_lo, boxes_hi)
    pieces = [int(p) for p in np.asarray(pieces)]
    q, succ = seed["q"], seed["succeeded"]
    row_q, col_q, diag_q = q[s].copy(), q[:, s].copy(), q[s, s]
    row_e, col_e = succ[s].copy(), succ[:, s].copy()
    row_r, row_u = seed["reachable"][s].copy(), seed["unreachable"][s].copy()
    for p in pieces:
        q[p] = row_q
        if q_columns == "copy":
            q[:, p] = col_q
        elif q_columns == "zero" or p != s:
            q[:, p] = 0.0
        succ[p], succ[:, p] = row_e, col_e
        seed["reachable"][p], seed["unreachable"][p] = row_r, row_u
        seed["blocked"][p] = False
    for p in pieces:
        for a in pieces:
            q[p, a], succ[p, a] = (diag_q if q_columns == "copy" else q[p, a]), False
        seed["reachable"][:, p] = False
        seed["unreachable"][:, p] = False
        seed["blocked"][:, p] = False
        if "records" in seed and (records == "cleared" or p != s):
            seed["records"][p], seed["records"][:, p] = 0, 0
        if "pair_count" in seed and p != s:
            seed["pair_count"][p], seed["pair_count"][:, p] = 0, 0
    group = pieces
    if q_rows == "aliased":
        alias = seed["alias"]
        alias[pieces] = alias[s]
        group = np.flatnonzero(alias == alias[s])
    if s == d:
        # An exit analysis (GARA's exit_analysis): the verdicts are about the exit box, not
        # about piece s, so the others keep their copied Q rows and edges towards it.
        seed["reachable"][s, s] = True
        return "split"
    for n, p in enumerate(pieces):
        hits = n < n_reach
        seed["reachable"][p, d], seed["unreachable"][p, d] = hits, not hits
        succ[p, d] = hits
        if not hits and q_rows != "kept":
            # The reference's rows are one object: the zero reaches every row of the group.
            q[group if q_rows != "copied" else p, d] = 0.0
    return "split"
