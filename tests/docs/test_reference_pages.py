"""The generated reference pages (scenario file, command line) are the committed ones."""

from __future__ import annotations

from pathlib import Path

import pytest

from vcfusion import reference
from vcfusion.commands import build_parser
from vcfusion.scenario import Scenario

REFERENCE = Path(__file__).resolve().parents[2] / "docs" / "reference"
REGENERATE = "python -m vcfusion.reference --write docs/reference/"


@pytest.mark.parametrize("name", [reference.SCENARIO_PAGE, reference.CLI_PAGE])
def test_committed_page_is_the_generated_one(name):
    generated = reference.pages(build_parser())[name]
    committed = (REFERENCE / name).read_text(encoding="utf-8")
    assert committed == generated, f"docs/reference/{name} is out of date: run `{REGENERATE}` and commit it"


def _fields(model, prefix=""):
    for name, field in model.model_fields.items():
        if field.exclude:
            continue
        subs = reference._submodels(field.annotation)
        if subs:
            yield from _fields(subs[0], f"{prefix}{name}.")
        else:
            yield f"{prefix}{name}", field


def test_every_scenario_field_is_described_on_the_page():
    page = reference.scenario_reference()
    fields = list(_fields(Scenario))
    assert len(fields) > 60
    for path, field in fields:
        assert field.description, f"scenario field {path} has no description= in vcfusion/scenario.py"
        assert f"| `{path.rsplit('.', 1)[-1]}` |" in page, path


def test_units_follow_the_field_names():
    assert reference.unit_of("step_s") == "s"
    assert reference.unit_of("gnss_noise_std_m") == "m"
    assert reference.unit_of("speed_mps") == "m/s"
    assert reference.unit_of("hfov_deg") == "°"
    assert reference.unit_of("tau_a_ticks") == "V2C ticks"
    assert reference.unit_of("count") == ""
    page = reference.scenario_reference()
    assert "| `step_s` | number | `0.01` | s | &gt; 0 |" in page


def test_cli_page_lists_every_command_and_option():
    parser = build_parser()
    page = reference.cli_reference(parser)
    for name, sub, _ in reference._subparsers(parser):
        assert f"## `vcfusion {name}`" in page
        for action in sub._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert f"`{option}`" in page, (name, option)
    assert "/work/" not in page and "/home/" not in page  # no machine paths in shipped defaults


def test_cli_page_shows_help_as_the_command_line_prints_it():
    # argparse %-formats every help string: a help written "95%% CIs" prints "95% CIs"
    import argparse

    parser = argparse.ArgumentParser(prog="vcfusion")
    parser.add_argument("--device", help="where it runs (default: %(default)s)", default="auto")
    sub = parser.add_subparsers(dest="command")
    p = sub.add_parser("matrix", help="tables with 95%% CIs")
    p.add_argument("--level", help="share in %%, above 50%% of drawn")
    page = reference.cli_reference(parser)
    assert "tables with 95% CIs" in page and "share in %, above 50% of drawn" in page and "%%" not in page
    # the options of the command itself, given before a subcommand, have their own table
    assert "| `--device` `DEVICE` | where it runs (default: auto) |" in page
    assert "95% CIs" in reference.cli_reference(build_parser()) and "`--device`" in reference.cli_reference(build_parser())
