"""The verb group loads a verb's module only when the verb is used: ``--help`` stays light."""

from __future__ import annotations

import subprocess
import sys

import click
from click.testing import CliRunner

from hartrao_jax.cli import VERBS, main


def test_every_verb_loads_and_its_short_help_is_the_listed_one():
    for name, (_, short) in VERBS.items():
        cmd = main.get_command(click.Context(main), name)
        assert cmd is not None, name
        for limit in (30, 45, 60, 200):
            assert (click.Command(name, help=short).get_short_help_str(limit)
                    == cmd.get_short_help_str(limit)), (name, limit)


def test_group_help_lists_every_verb():
    out = CliRunner().invoke(main, ["--help"]).output
    for name in VERBS:
        assert f"  {name} " in out


def test_help_imports_no_verb_module():
    code = ("import sys\nfrom hartrao_jax.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in sys.modules if m.startswith(('hartrao_jax.report', "
            "'hartrao_jax.diagnose', 'hartrao_jax.prove', 'hartrao_jax.surface', "
            "'hartrao_jax.cli._pipeline', 'hartrao_jax.cli._demo', 'hartrao_jax.cli._campaign'))]\n"
            "print('HEAVY', heavy)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "HEAVY []" in out.stdout, out.stdout[-500:]
