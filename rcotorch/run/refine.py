"""Run any refinement graph built in Python through the same machinery as ``rcotorch run``.

``refine(graph, steps, estimates=..., truth=...)`` steps the graph with member health checks, TensorBoard
logs, checkpoints, figures and ``summary.json`` in an output folder, and returns a ``RefinementResult``: the
estimates with their confidence intervals, whether the data determined them, each member's status and the
requirements' pass/fail. A scenario is a declaration of the same thing (``rcotorch.run.scenario.Scenario``): a
named graph with default settings; ``GraphScenario`` is the declaration of one graph that is already built.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from ..errors import ConfigError, OutputError
from ..graph import Graph
from ..verdict import intervals as ci
from ..verdict.health import Criteria
from .runner import DTYPES, Run, result_table
from .scenario import Requirement, Scenario

Estimate = Callable[[Graph], torch.Tensor]


def parameter_estimates(graph: Graph) -> dict[str, torch.Tensor]:
    """The estimator's free parameters, each a (B,) tensor named after the entries of theta it sets
    (``theta[y0(k)]``): the default estimates of a graph."""
    est = graph.role("estimator")
    eta = est.theta_free()
    return {f"theta[{name}]": eta[:, j] for j, name in enumerate(est.theta_names)}


class GraphScenario(Scenario):
    """A scenario made of one graph that is already built: its estimates (functions of the graph, each
    returning a (B,) tensor), truth, requirements, scales, units and the names of its measured outputs. It has no
    settings of its own; its batch, dtype and device are the graph's. The estimator's options are the graph's
    own (no settings). Its name is ``name``, or 'refinement' where none is given; the figures show the name
    given (``figure_name``), and no name where there is none."""

    estimator_options = ()

    def __init__(self, graph: Graph, estimates: Mapping[str, Estimate] | None = None,
                 truth: Mapping[str, float | Sequence[float]] | None = None,
                 requirements: Sequence[Requirement] = (), scales: Mapping[str, float] | None = None,
                 units: Mapping[str, str] | None = None, name: str | None = None, metrics=None,
                 steps: int = 10000, validation: Mapping[str, Any] | None = None,
                 truth_history: Mapping[str, Sequence[tuple[float, float]]] | None = None,
                 physics: Callable[[dict[str, torch.Tensor]], Graph] | None = None,
                 output_names: Sequence[str] | None = None):
        if not isinstance(graph, Graph):
            raise ConfigError(f"refine: expected an rcotorch Graph, got {type(graph).__name__}")
        if "estimator" not in graph.roles or "error" not in graph.roles:
            raise ConfigError("refine: the graph needs the roles 'estimator' and 'error' (rcotorch.refinement "
                              f"declares them; Graph(..., roles=...) otherwise); it has {sorted(graph.roles)}")
        self.graph, self.name, self.steps = graph, name or "refinement", steps
        self.figure_name = name or ""
        self._output_names = [str(n) for n in output_names] if output_names is not None else []
        width = None
        if "measured" in graph.roles:
            block, port = graph.role_signal("measured")
            width = graph.blocks[block].outputs.get(port)
        if self._output_names and width is not None and len(self._output_names) != width:
            raise ConfigError(f"refine: output_names names {len(self._output_names)} outputs, but the graph "
                              f"measures {width}")
        self._validation = None if validation is None else dict(validation)
        self.description = f"a graph built in Python ({len(graph.blocks)} blocks)"
        self._estimates = dict(estimates) if estimates is not None else None
        self._truth = dict(truth or {})
        self._history = dict(truth_history or {})
        for key, pairs in self._history.items():         # the truth at the end: the history's last value
            if key not in self._truth and pairs:
                self._truth[key] = list(pairs)[-1][1]
        self._metrics = metrics
        self._physics = physics
        self.requirements = tuple(requirements)
        self._scales = dict(scales or {})
        self.units = dict(units or {})
        if "y" not in self.units and "measured" in graph.roles:   # the measured output's unit, from a recording
            name, port = graph.role_signal("measured")
            units = getattr(graph.blocks[name], "units", None)
            if isinstance(units, dict) and isinstance(units.get(port), str):
                self.units["y"] = units[port]
        known = set(self.estimates(graph, {}))
        for key in list(self._truth) + list(self._scales) + list(self._history):
            if key not in known:
                raise ConfigError(f"refine: truth or scale given for {key!r}, which is not an estimate; the "
                                  f"estimates are {sorted(known)}")
        for req in self.requirements:
            group, _, key = req.key.partition(".")
            if group == "estimates" and key not in known:
                raise ConfigError(f"refine: requirement on {req.key!r}, which is not an estimate; the estimates "
                                  f"are {sorted(known)}")

    def build(self, settings, batch, dtype, device) -> Graph:
        g = self.graph
        if batch != g.batch_size:
            raise ConfigError(f"refine: the graph has {g.batch_size} members, not {batch}")
        return g

    def truth(self, settings) -> dict[str, Any]:
        return dict(self._truth)

    def truth_history(self, settings) -> dict[str, list[tuple[float, float]]]:
        return {k: list(v) for k, v in self._history.items()}

    def validation(self, graph: Graph, settings) -> dict[str, Any] | None:
        if self._validation is not None:
            return dict(self._validation)
        return super().validation(graph, settings)

    def estimates(self, graph: Graph, settings) -> dict[str, torch.Tensor]:
        if self._estimates is None:
            return parameter_estimates(graph)
        return {key: _per_member("estimate", key, fn, graph) for key, fn in self._estimates.items()}

    def physics(self, settings, estimates, batch, dtype, device) -> Graph | None:
        return None if self._physics is None else self._physics(dict(estimates))

    def metrics(self, graph: Graph, settings) -> dict[str, torch.Tensor]:
        return {key: _per_member("metric", key, fn, graph) for key, fn in (self._metrics or {}).items()}

    def scales(self, settings) -> dict[str, float]:
        return dict(self._scales)

    def output_names(self, settings) -> list[str]:
        return list(self._output_names)


def _per_member(kind: str, key: str, fn, graph: Graph) -> torch.Tensor:
    """``fn(graph)`` (an estimate's or metric's function, ``_call``) as one value per member, (B,)."""
    value = _call(kind, key, fn, graph)
    if value.numel() != graph.batch_size:
        raise ConfigError(f"refine: {kind} {key!r} gives {tuple(value.shape)}, expected one value per member "
                          f"({graph.batch_size},)")
    return value.reshape(graph.batch_size)


def _call(kind: str, key: str, fn: Estimate, graph: Graph) -> torch.Tensor:
    """An estimate's or a metric's function of the graph, called; what it raises is a ConfigError that names it
    (the exception is its cause)."""
    try:
        value = fn(graph)
    except (MemoryError, torch.OutOfMemoryError):
        raise
    except Exception as e:
        raise ConfigError(f"refine: {kind} {key!r}: its function raised {type(e).__name__}: {e}") from e
    try:
        return torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ConfigError(f"refine: {kind} {key!r}: its function returned {type(value).__name__}, not one number "
                          f"per member ({e})") from e


class RefinementResult:
    """What a refinement found, like a scipy or python-control result object.

    ``refine`` makes it; printing it prints the table of estimates, intervals, status and requirements.

    Parameters
    ----------
    run : rcotorch.run.runner.Run
        The finished run.
    summary : Mapping[str, Any]
        The run's ``summary.json`` as a dict.

    Attributes
    ----------
    estimates : dict[str, torch.Tensor]
        Key -> (B,) float64, the final estimates.
    lower, upper : dict[str, torch.Tensor]
        Key -> (B,), the confidence interval of each estimate (NaN where none).
    level : float or None
        The intervals' confidence level (None without intervals).
    status : list of str
        One word per member: ``converged``, ``undetermined`` (settled, but the data did not determine an
        estimate), ``biased`` (settled and determined, but an estimate carries a bias beyond its interval:
        ``summary['intervals'][key]['bias']`` gives its size and sign, ``summary['health']['bias_reason']`` its
        cause), ``not_converged`` or ``diverged``.
    determined : torch.Tensor
        (B,) bool, whether the data determined every estimate of the member.
    passed : dict[str, torch.Tensor]
        Requirement key -> (B,) bool, each member's pass or fail.
    summary : dict
        The run's ``summary.json`` as a dict.
    out : pathlib.Path
        The folder it was written to.
    run : rcotorch.run.runner.Run
        The run, for its graph and history.
    """

    def __init__(self, run: Run, summary: Mapping[str, Any]):
        self.run, self.summary, self.out = run, dict(summary), run.out
        B = run.batch

        def tensor(values) -> torch.Tensor:
            values = values if isinstance(values, list) else [values]
            return torch.tensor([float("nan") if v is None else v for v in values], dtype=torch.float64)
        self.estimates = {k: tensor(v) for k, v in summary["estimates"].items()}
        ivs = summary.get("intervals") or {}
        nan = torch.full((B,), float("nan"), dtype=torch.float64)
        self.lower = {k: tensor(ivs[k]["lower"]) if k in ivs else nan.clone() for k in self.estimates}
        self.upper = {k: tensor(ivs[k]["upper"]) if k in ivs else nan.clone() for k in self.estimates}
        self.level = next(iter(ivs.values()))["level"] if ivs else None
        status = summary["health"]["status"]
        self.status = status if isinstance(status, list) else [status]
        det = summary["health"].get("determined")
        self.determined = torch.tensor(det if isinstance(det, list) else [bool(det)] * B, dtype=torch.bool) \
            if det is not None else torch.zeros(B, dtype=torch.bool)
        self.passed = {}
        for key, chk in summary.get("requirements", {}).items():
            per = chk.get("member_pass", chk["pass"])
            self.passed[key] = torch.tensor(per if isinstance(per, list) else [per], dtype=torch.bool)

    @property
    def half_width(self) -> dict[str, torch.Tensor]:
        """Key -> (B,), half the width of each estimate's confidence interval (NaN where none)."""
        return {k: (self.upper[k] - self.lower[k]) / 2 for k in self.estimates}

    @property
    def success(self) -> bool:
        """Every member converged with determined estimates and every requirement passed."""
        return all(s == "converged" for s in self.status) and all(bool(p.all()) for p in self.passed.values())

    def __str__(self) -> str:
        return result_table(self.summary)

    def __repr__(self) -> str:
        return f"<RefinementResult {self.summary['scenario']}: batch {self.run.batch}, {self.out}>\n{self}"


def refine(graph: Graph, steps: int, estimates: Mapping[str, Estimate] | None = None, *,
           truth: Mapping[str, float | Sequence[float]] | None = None, requirements: Sequence[Requirement] = (),
           scales: Mapping[str, float] | None = None, units: Mapping[str, str] | None = None,
           metrics: Mapping[str, Estimate] | None = None, name: str | None = None,
           out: str | Path | None = None, overwrite: bool = False, level: float = ci.LEVEL,
           intervals: bool = True, figures: bool = True, progress: bool | None = None,
           checkpoint_every: int | None = None, health: Criteria | None = None,
           validation: bool | Mapping[str, Any] = True,
           truth_history: Mapping[str, Sequence[tuple[float, float]]] | None = None,
           log_every: int | None = None,
           physics: Callable[[dict[str, torch.Tensor]], Graph] | None = None,
           output_names: Sequence[str] | None = None) -> RefinementResult:
    """Run ``graph`` (made by ``rcotorch.refinement``, or any graph with the roles 'estimator' and 'error')
    for ``steps`` steps as ``rcotorch run`` runs a scenario, and return what it found.

    Parameters
    ----------
    graph : Graph
        A fresh graph (step 0); its batch, dtype and device are the run's.
    steps : int
        Steps to run.
    estimates : {name: function(graph) -> (B,) tensor}, optional
        What the refinement estimates, as functions of the graph, e.g.
        ``{'dK': lambda g: -g.role('estimator').dc_gain()[:, 0, 0]}``. Default: the estimator's free
        parameters (``theta[...]``).
    truth : {name: value or one value per member}, optional
        The true values where they are known (a simulated truth); they appear beside the estimates.
    requirements : sequence of ``rcotorch.run.scenario.Requirement``
        Acceptance bounds, e.g. ``Requirement('estimates.dK', 'abs_err', 0.01)``, checked per member.
    scales : {name: size}, optional
        A size for an estimate that may be near zero, against which its interval is judged (an estimate is
        determined when its interval's half-width is at most half of max(|estimate|, scale)).
    units, metrics : optional
        Units of estimates; further final metrics as functions of the graph.
    name, out, overwrite : optional
        The run's name (default 'refinement') and output folder (default ``runs/NAME``, or ``runs/NAME-2``,
        ...). The figures' titles start with the name given, else with the output folder's name where ``out``
        is given, else with neither.
    level : float
        Confidence level of the intervals (0.95).
    intervals, figures, progress, checkpoint_every, health : optional
        As for ``rcotorch run``: whether to compute intervals and draw figures, a progress bar, periodic
        checkpoints, and the health criteria.
    validation : bool or {argument: value}
        Validate the refined model on held-out data at the end (``rcotorch.validate``; metrics
        ``validation_rmse``, ``validation_fit_percent`` and the initial model's): True for 2000 steps of a
        fresh excitation of a simulated physical system, or the arguments of ``rcotorch.validate``, e.g.
        ``{'rows': (20000, 30000)}`` for a later window of recorded data; False for none.
    truth_history : {name: [(time, value), ...]}, optional
        A truth that changes during the run (a simulated fault): the value from each time on, in time order
        (seconds where the graph has a sample time, else steps), e.g. ``{'dk2': [(0, 0.0), (60, -0.2)]}``. Its
        last value is its ``truth``; the summary and the requirements take the value at the run's end (a run
        that stops before a change is judged against the value before it); TensorBoard and the figures draw it
        as it was at each time and mark each change (and each change detector's alarms).
    log_every : int, optional
        Steps between logs (TensorBoard and the figures' history); by default as many as take about a tenth of
        the run's time, at least 20, or 250 where the run follows a change (docs/cli.md).
    physics : callable, optional
        ``physics(estimates)`` -> a graph built as ``graph`` was, whose physical system (``physical=`` or
        ``truth=`` of ``rcotorch.refinement``) takes each member's estimates ({key: (B,) tensor}) as its
        parameters: the verdict simulates it to measure how far the refined model's estimates are from the
        physics' (a sampled or otherwise approximate model class), and calls a member ``biased`` where that
        exceeds its interval (docs/intervals.md).
    output_names : sequence of str, optional
        The names of the measured outputs, one per channel of the graph's measured signal (e.g. ``['floor 1',
        'floor 2', 'floor 3']``): the figures label each output and its residual with them (default 'y', or
        'y[0]', 'y[1]', ...).

    Returns
    -------
    RefinementResult
        Estimates, intervals, status and requirement checks per member; printing it prints the table.

    Raises
    ------
    ConfigError
        If the graph has already run, is not a ``Graph`` with the roles 'estimator' and 'error', its dtype is
        not one the runner knows, truth, scales, requirements or estimates do not fit the estimates, or
        output_names do not fit the measured outputs; or if an estimate's or a metric's function raises, when
        ``refine`` is called or during the run (the message names its key; its exception is the cause).
    """
    if int(graph.k) != 0:
        raise ConfigError(f"refine: the graph has already run {int(graph.k)} steps; pass a fresh graph (or call "
                          "graph.reset())")
    sc = GraphScenario(graph, estimates, truth=truth, requirements=requirements, scales=scales, units=units,
                       name=name, metrics=metrics, steps=steps,
                       validation=validation if isinstance(validation, Mapping) else None,
                       truth_history=truth_history, physics=physics, output_names=output_names)
    if name is None and out is not None:           # the figures are titled with the folder the user named
        sc.figure_name = Path(out).name
    dtype = _dtype_name(graph)
    device = str(graph.k.device)
    try:
        run = Run(sc, steps=steps, batch=graph.batch_size, dtype=dtype, device=device, out=out, overwrite=overwrite,
                  health=health, intervals=intervals, level=level, validation=bool(validation), log_every=log_every)
        run.figures_expected = bool(figures)
        try:
            run.advance(progress=progress, checkpoint_every=checkpoint_every)
            summary = run.finish(figures=figures)
        finally:
            run.close()
    except OutputError as e:                    # said in this function's arguments, not the command line's
        raise type(e)(_in_arguments(str(e))) from None
    return RefinementResult(run, summary)


def _in_arguments(message: str) -> str:
    """An output folder's error as a caller of ``refine`` acts on it: its arguments, not the command's options."""
    for option, argument in (("use --resume to continue it, --overwrite to replace it, or choose another --out",
                              "pass overwrite=True to replace it, or choose another out"),
                             ("--overwrite", "overwrite=True"), ("another --out", "another out"), ("--out", "out")):
        message = message.replace(option, argument)
    return message


def _dtype_name(graph: Graph) -> str:
    for t in graph.buffers():
        if t.is_floating_point():
            for key, value in DTYPES.items():
                if value == t.dtype:
                    return key
            raise ConfigError(f"refine: the graph's dtype {t.dtype} is not one of {sorted(DTYPES)}")
    return "float64"
