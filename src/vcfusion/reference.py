"""Reference pages of the documentation, generated from the code so that they cannot drift from it.

- `scenario_reference()`: every field of a scenario file, walked recursively from the pydantic
  models of `vcfusion.scenario` (type, default, unit, constraints, description).
- `cli_reference(parser)`: every command and option of the `vcfusion` command line, walked from
  the argparse parser.

`python -m vcfusion.reference --write docs/reference/` writes both pages (`make docs` runs it
before mkdocs); `tests/docs/test_reference_pages.py` regenerates them in memory and compares them
with the committed ones.

Units come from the field names: a field's last name part gives its unit (`_s` seconds, `_m`
metres, `_mps` m/s, `_deg` degrees, `_px` pixels, `_ticks` V2C ticks, `vehs_per_hour` vehicles per
hour); a field without such a suffix is a count, a flag, a probability or a name, as its type says.
"""

from __future__ import annotations

import argparse
import enum
import sys
import types
import typing
from pathlib import Path, PurePath

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo

SCENARIO_PAGE = "scenario.md"
CLI_PAGE = "cli.md"

# unit by the field name's suffix (the naming convention of vcfusion.scenario)
UNIT_SUFFIXES = (
    ("_mps2", "m/s²"),
    ("_mps", "m/s"),
    ("_deg", "°"),
    ("_px", "px"),
    ("_ticks", "V2C ticks"),
    ("_s", "s"),
    ("_m", "m"),
)
UNIT_NAMES = {"vehs_per_hour": "veh/h"}

# Rules that tie fields together (the model validators of vcfusion.scenario); kept beside the
# generator because a validator's code cannot be read back as text.
CROSS_FIELD_RULES = (
    "`simulation.step_s` is a whole number of milliseconds, at least 0.001 s (SUMO's time resolution).",
    "`v2c.period_s`, `ar.period_s` and `simulation.trajectory_period_s` are whole multiples of "
    "`simulation.step_s`; `simulation.max_time_s` is at least one step.",
    "`simulation.trajectory_period_s` is at most 1 s while `metrics.enabled` (MOVESTAR rates every second).",
    "`v2c.twin_timeout_s` is more than `v2c.latency_s` + 3 `v2c.jitter_s` + `v2c.period_s`.",
    "`ar.medium_threshold` <= `ar.high_threshold`; with `fusion.enabled`, `ar.period_s` is a whole multiple "
    "of `v2c.period_s`.",
    "`vision.enabled` needs an `ego` block; `fusion.enabled` needs `vision.enabled`; `ar.video` needs "
    "`fusion.enabled` and `vision.only_when_warning: false`.",
    "`fusion.detector: onnx-yolo` needs `fusion.weights`; `detector: oracle` takes no weights; "
    "`yolo_input_px` / `yolo_classes` other than their defaults only with `onnx-yolo`.",
    "`camera.far_m` > `camera.near_m`; `vehicles[].pos_m` is [low, high] with low <= high.",
    "At least one of `ego`, `vehicles`, `flows`.",
    "Every file named (network, vehicle types, lane-change model, detector weights) is read on load; "
    "lanes, edges, positions and vehicle types are checked against them; a departure speed above the "
    "vehicle type's `maxSpeed` is refused; commands that render refuse a network with elevation and "
    "vehicle classes the camera does not draw.",
)


def unit_of(name: str) -> str:
    """The unit of a scenario field by its name (the module doc's convention); '' for none."""
    if name in UNIT_NAMES:
        return UNIT_NAMES[name]
    for suffix, unit in UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    return ""


def _md(text: str) -> str:
    """Text safe inside a markdown table cell."""
    return " ".join(str(text).split()).replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def _constraints(metadata) -> list[str]:
    out = []
    for m in metadata:
        if isinstance(m, FieldInfo):  # Field(ge=...) inside Annotated[...]
            out += _constraints(m.metadata)
        elif isinstance(m, annotated_types.Ge):
            out.append(f">= {m.ge:g}")
        elif isinstance(m, annotated_types.Gt):
            out.append(f"> {m.gt:g}")
        elif isinstance(m, annotated_types.Le):
            out.append(f"<= {m.le:g}")
        elif isinstance(m, annotated_types.Lt):
            out.append(f"< {m.lt:g}")
        elif isinstance(m, annotated_types.MinLen):
            out.append(f"at least {m.min_length} item{'s' if m.min_length != 1 else ''}"
                       if m.min_length != 1 else "not empty")
        elif isinstance(m, annotated_types.MaxLen):
            out.append(f"at most {m.max_length} items")
    return out


def _type_text(tp) -> tuple[str, list[str]]:
    """(readable type, constraints found inside it) of an annotation."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Annotated:
        inner, cons = _type_text(args[0])
        return inner, cons + _constraints(args[1:])
    if origin in (typing.Union, types.UnionType):
        parts, cons = [], []
        nullable = False
        for a in args:
            if a is type(None):
                nullable = True
                continue
            t, c = _type_text(a)
            parts.append(t)
            cons += c
        return " or ".join(parts) + (" or null" if nullable else ""), cons
    if origin is typing.Literal:
        return "one of " + ", ".join(f"`{a}`" for a in args), []
    if origin is list:
        t, c = _type_text(args[0])
        return f"list of {t}", [f"each {x}" for x in c]
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            t, c = _type_text(args[0])
            return f"list of {t}", [f"each {x}" for x in c]
        texts = [_type_text(a) for a in args]
        if len({t for t, _ in texts}) == 1:
            cons = texts[0][1]
            return f"[{texts[0][0]}, {texts[0][0]}]" if len(args) == 2 else f"{len(args)} × {texts[0][0]}", \
                [f"each {x}" for x in cons]
        return "[" + ", ".join(t for t, _ in texts) + "]", [x for _, c in texts for x in c]
    if origin is dict:
        k, _ = _type_text(args[0])
        v, c = _type_text(args[1])
        return f"mapping {k} → {v}", c
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return f"[{_model_title(tp)}](#{_anchor(tp)})", []
    if tp is bool:
        return "boolean", []
    if tp is int:
        return "integer", []
    if tp is float:
        return "number", []
    if tp is str:
        return "text", []
    if isinstance(tp, type) and issubclass(tp, PurePath):
        return "path", []
    return getattr(tp, "__name__", str(tp)), []


def _default_text(field: FieldInfo) -> str:
    if field.is_required():
        return "required"
    if field.default_factory is not None:
        value = field.default_factory()
    else:
        value = field.default
    return _value_text(value)


def _value_text(value) -> str:
    if value is None:
        return "`null`"
    if isinstance(value, BaseModel):
        return "(block defaults)"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, enum.Enum):
        return f"`{value.value}`"
    if isinstance(value, float):
        return f"`{value:g}`"
    if isinstance(value, (tuple, list)):
        return "`[" + ", ".join(_value_text(v).strip("`") for v in value) + "]`"
    if isinstance(value, dict):
        return "`{" + ", ".join(f"{k}: {_value_text(v).strip('`')}" for k, v in value.items()) + "}`"
    if isinstance(value, str):
        return f'`"{value}"`' if value == "" else f"`{value}`"
    return f"`{value}`"


def _model_title(model: type[BaseModel]) -> str:
    return _MODEL_PATHS.get(model, model.__name__)


def _anchor(model: type[BaseModel]) -> str:
    return _MODEL_PATHS.get(model, model.__name__).replace("[]", "").replace(".", "-").replace(" ", "-").lower() \
        if model in _MODEL_PATHS else model.__name__.lower()


_MODEL_PATHS: dict[type[BaseModel], str] = {}


def _submodels(tp) -> list[type[BaseModel]]:
    """The pydantic models an annotation holds (directly, in a list or as an option)."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return [tp]
    return [m for a in typing.get_args(tp) for m in _submodels(a)]


def _is_list_of_models(tp) -> bool:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_is_list_of_models(a) for a in typing.get_args(tp))
    return origin is list and any(_submodels(a) for a in typing.get_args(tp))


def _walk(model: type[BaseModel], path: str, out: list[tuple[str, type[BaseModel]]]) -> None:
    _MODEL_PATHS[model] = path
    out.append((path, model))
    for name, field in model.model_fields.items():
        if field.exclude:
            continue
        for sub in _submodels(field.annotation):
            if sub not in _MODEL_PATHS:
                _walk(sub, f"{name}[]" if _is_list_of_models(field.annotation) else name, out)


def scenario_reference() -> str:
    """The scenario reference page (markdown), from the models of vcfusion.scenario."""
    from vcfusion.scenario import Scenario

    _MODEL_PATHS.clear()
    models: list[tuple[str, type[BaseModel]]] = []
    _walk(Scenario, "top level", models)
    lines = [
        "# Scenario reference",
        "",
        "<!-- generated by `python -m vcfusion.reference --write docs/reference/` from "
        "src/vcfusion/scenario.py; do not edit -->",
        "",
        "A scenario is a YAML file validated on load: unknown keys, wrong types and values outside "
        "the constraints below are refused (exit code 2, one line per problem naming the file and the "
        "field). Paths are relative to the file that sets them; a file may `extends:` another "
        "([Getting started](../getting-started.md#writing-a-scenario)). Numbers are finite. "
        "Units follow the field names: `_s` seconds, `_m` metres, `_mps` m/s, `_deg` degrees, `_px` "
        "pixels, `_ticks` V2C ticks.",
        "",
        "Lanes are **tracks** of the route, indexed from the right (0 = rightmost); positions are "
        "along the route (front bumper).",
        "",
    ]
    for path, model in models:
        lines += [f"## {path}" if path == "top level" else f"## `{path}`", ""]
        if model.__doc__:
            lines += [" ".join(model.__doc__.split()), ""]
        lines += ["| field | type | default | unit | constraints | description |",
                  "|---|---|---|---|---|---|"]
        for name, field in model.model_fields.items():
            if field.exclude:
                continue
            type_text, cons = _type_text(field.annotation)
            cons = _constraints(field.metadata) + cons
            lines.append(f"| `{name}` | {_md(type_text)} | {_md(_default_text(field))} | {unit_of(name)} | "
                         f"{_md('; '.join(cons))} | {_md(field.description or '')} |")
        lines.append("")
    lines += ["## Rules across fields", ""] + [f"- {rule}" for rule in CROSS_FIELD_RULES] + [""]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# command line

def _default_of(action: argparse.Action) -> str:
    d = action.default
    if d is None or d is argparse.SUPPRESS or isinstance(action, (argparse._StoreTrueAction,
                                                                  argparse._StoreFalseAction)):
        return ""
    if isinstance(d, list) and not d:
        return ""
    if isinstance(d, str) and Path(d).is_absolute():
        # a file shipped with vcfusion: its place inside the package or checkout, not this machine's
        parts = Path(d).parts
        return f"`{'/'.join(parts[-2:])}` (shipped)"
    return f"`{d}`"


def _metavar(action: argparse.Action) -> str:
    if action.metavar is not None:
        return action.metavar if isinstance(action.metavar, str) else " ".join(action.metavar)
    if action.choices is not None and not isinstance(action, argparse._SubParsersAction):
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    return action.dest.upper()


def _takes_value(action: argparse.Action) -> bool:
    return action.nargs != 0


def _arg_text(action: argparse.Action) -> str:
    mv = _metavar(action)
    if action.nargs == "?":
        return f"[{mv}]"
    if action.nargs == "+":
        return f"{mv} [{mv} ...]"
    if action.nargs == "*":
        return f"[{mv} ...]"
    return mv


def _synopsis(parser: argparse.ArgumentParser) -> str:
    """A usage line built here (argparse's own wraps by the terminal and differs between Pythons)."""
    parts = [parser.prog]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.help is argparse.SUPPRESS:
            continue
        if isinstance(action, argparse._SubParsersAction):
            parts.append("COMMAND")
            continue
        if not action.option_strings:
            parts.append(_arg_text(action))
            continue
        flag = action.option_strings[-1] if action.option_strings[-1].startswith("--") else action.option_strings[0]
        text = f"{flag} {_arg_text(action)}" if _takes_value(action) else flag
        parts.append(text if action.required else f"[{text}]")
    return " ".join(parts)


def _help_text(action: argparse.Action) -> str:
    """The help as `vcfusion --help` prints it: argparse %-formats every help string (so a
    literal percent sign is written %%)."""
    text = action.help or ""
    if "%" in text:
        text = text % {**vars(action), "prog": "vcfusion"}
    return text


def _subparsers(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: _help_text(a) for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield name, sub, helps.get(name, "")


def _command_section(parser: argparse.ArgumentParser, summary: str, level: int) -> list[str]:
    lines = [f"{'#' * level} `{parser.prog}`", ""]
    if summary:
        lines += [_md(summary)[:1].upper() + _md(summary)[1:] + ".", ""]
    lines += ["```text", _synopsis(parser), "```", ""]
    lines += _argument_table(parser)
    for name, sub, help_text in _subparsers(parser):
        lines += _command_section(sub, help_text, level + 1)
    return lines


def _argument_table(parser: argparse.ArgumentParser) -> list[str]:
    """The parser's own arguments as a markdown table (none: no lines)."""
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)) or action.help is argparse.SUPPRESS:
            continue
        if action.option_strings:
            name = ", ".join(f"`{o}`" for o in action.option_strings)
            if _takes_value(action):
                name += f" `{_arg_text(action)}`"
        else:
            name = f"`{_arg_text(action)}`"
        notes = []
        if action.required and action.option_strings:
            notes.append("required")
        if action.choices is not None:
            notes.append("one of " + ", ".join(f"`{c}`" for c in action.choices))
        if isinstance(action, argparse._AppendAction):
            notes.append("repeatable")
        rows.append(f"| {name} | {_md(_help_text(action))} | {_default_of(action)} | {'; '.join(notes)} |")
    if not rows:
        return []
    return ["| argument | meaning | default | notes |", "|---|---|---|---|"] + rows + [""]


def cli_reference(parser: argparse.ArgumentParser) -> str:
    """The command-line reference page (markdown), from the argparse parser."""
    lines = [
        "# Command-line reference",
        "",
        "<!-- generated by `python -m vcfusion.reference --write docs/reference/` from the argparse "
        "parser; do not edit -->",
        "",
        "Every command exits with 0 on success, 2 on bad input (one line per problem naming the file, "
        "field or option), 1 when a run or a worker's job failed, 130 on Ctrl-C and 143 on SIGTERM.",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    for name, _, help_text in _subparsers(parser):
        lines.append(f"| [`{name}`](#{('vcfusion-' + name).replace(' ', '-')}) | {_md(help_text)} |")
    lines += ["", "Options of `vcfusion` itself, given before the command (`vcfusion --device cpu run ...`):", ""]
    lines += _argument_table(parser)
    for name, sub, help_text in _subparsers(parser):
        lines += _command_section(sub, help_text, 2)
    return "\n".join(lines)


def pages(parser: argparse.ArgumentParser | None = None) -> dict[str, str]:
    """{file name: markdown} of the generated reference pages."""
    if parser is None:
        from vcfusion.commands import build_parser

        parser = build_parser()
    return {SCENARIO_PAGE: scenario_reference(), CLI_PAGE: cli_reference(parser)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vcfusion.reference", description=__doc__.splitlines()[0])
    ap.add_argument("--write", metavar="DIR", help="write the pages into DIR (else print them)")
    args = ap.parse_args(argv)
    for name, text in pages().items():
        if args.write:
            out = Path(args.write)
            out.mkdir(parents=True, exist_ok=True)
            (out / name).write_text(text, encoding="utf-8")
            print(f"wrote {out / name}")
        else:
            sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
