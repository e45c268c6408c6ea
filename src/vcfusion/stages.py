"""What the stages of a run declare, and the check of their wiring when the run is built.

A stage is a tick hook, the ego controller or a cloud process model. It declares, as class or
instance attributes (all optional, empty when absent):

- ``needs``: fields of :class:`vcfusion.cosim.Tick` it reads;
- ``provides``: fields it sets (the field may stay None at ticks where it has nothing);
- ``fills``: fields it sets only where no earlier stage did (a fallback, e.g. the cloud guidance
  when no overlay made any): it must come after every stage that provides them;
- ``table``: the run table its per-tick rows go to (tick hooks);
- ``finish(tables, summary)``: an end-of-run step (e.g. the driver's tables and summary, the cloud's
  lane-change flags), with ``finish_needs`` (tables it reads), ``finish_tables`` (tables it adds)
  and ``finish_summary`` (summary keys it adds).

Order: process models (they run inside the twin store, before the hooks), hooks in list order,
then the controller; ``finish`` runs in the same order, after the core tables and summary.
:func:`check_wiring` refuses a run whose stages would read a field or table that nothing earlier
provides, provide a field twice, or fill a field before its providers, naming the stage and what
is missing.
"""

from __future__ import annotations

# Tick fields the loop itself sets; the ego's only when the scenario has one.
LOOP_FIELDS = ("time", "truth", "twins")
EGO_FIELDS = ("ego", "neighbours")
STAGE_FIELDS = ("frame", "detections", "guidance")
TICK_FIELDS = LOOP_FIELDS + EGO_FIELDS + STAGE_FIELDS
# Tables every run writes before the stages' finish steps (cosim.CoSimulation.run)
CORE_TABLES = ("trajectories", "twins", "ego", "vehicles", "collisions", "lane_changes")


class WiringError(ValueError):
    """Stages put together in an order (or combination) that cannot work; the message names the
    stage and the missing input."""


def stage_name(stage) -> str:
    return getattr(stage, "name", None) or type(stage).__name__


def declared(stage, attribute: str) -> tuple[str, ...]:
    return tuple(getattr(stage, attribute, ()) or ())


def _claim(owners: dict[str, str], key: str, label: str, message: str) -> None:
    """Record `label` as the one owner of `key`; `message` ({owner} filled in) if it has one."""
    if key in owners:
        raise WiringError(message.replace("{owner}", owners[key]))
    owners[key] = label


def check_wiring(process_models: list[tuple[str, object]], hooks: list, controller, has_ego: bool) -> None:
    """Raise :class:`WiringError` unless every stage's inputs come from the loop or an earlier stage.
    `process_models`: (name, model) pairs, as the twin store takes them."""
    stages = [(f"process model {name} ({stage_name(m)})", m) for name, m in process_models]
    stages += [(f"tick hook {k} ({stage_name(h)})", h) for k, h in enumerate(hooks)]
    if controller is not None:
        stages.append((f"controller {stage_name(controller)}", controller))
    available = set(LOOP_FIELDS) | (set(EGO_FIELDS) if has_ego else set())
    providers: dict[str, str] = {f: "the tick loop" for f in available}
    filled: dict[str, str] = {}
    for label, stage in stages:
        for attribute in ("needs", "provides", "fills"):
            for f in declared(stage, attribute):
                if f not in TICK_FIELDS:
                    raise WiringError(f"{label}: {attribute} {f!r}: expected a Tick field, one of {TICK_FIELDS}")
        for f in declared(stage, "needs"):
            if f not in available:
                later = [lab for lab, s in stages if f in declared(s, "provides") + declared(s, "fills")]
                hint = (f"; {later[0]} provides it: put it before" if later else
                        "; the scenario has no ego" if f in EGO_FIELDS else "; no stage of this run provides it")
                raise WiringError(f"{label} needs {f!r}, which no earlier stage provides{hint}")
        for f in declared(stage, "provides"):
            if f in filled:
                raise WiringError(f"{label} provides {f!r} after {filled[f]}, which fills it only where no earlier "
                                  f"stage did: put {label} before it")
            _claim(providers, f, label, f"{label} provides {f!r}, which {{owner}} already provides")
        for f in declared(stage, "fills"):
            _claim(filled, f, label, f"{label} fills {f!r}, which {{owner}} already fills")
        available |= set(declared(stage, "provides")) | set(declared(stage, "fills"))
    check_finish(stages)


def check_finish(stages: list[tuple[str, object]]) -> None:
    tables = {t: "the run" for t in CORE_TABLES}
    for label, stage in stages:
        table = getattr(stage, "table", None)
        if table is not None:
            _claim(tables, table, label, f"{label}: table {table!r} is already written by {{owner}}")
    summary: dict[str, str] = {}
    for label, stage in stages:
        finishes = callable(getattr(stage, "finish", None))
        wanted = declared(stage, "finish_needs") + declared(stage, "finish_tables") + declared(stage, "finish_summary")
        if wanted and not finishes:
            raise WiringError(f"{label} declares end-of-run tables or summary keys but has no finish(tables, summary)")
        for t in declared(stage, "finish_needs"):
            if t not in tables:
                raise WiringError(f"{label} needs table {t!r} at the end of the run, which no earlier stage writes")
        for t in declared(stage, "finish_tables"):
            _claim(tables, t, label, f"{label}: table {t!r} is already written by {{owner}}")
        for key in declared(stage, "finish_summary"):
            _claim(summary, key, label, f"{label}: summary key {key!r} is already written by {{owner}}")
