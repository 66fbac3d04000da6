"""Command line of helixrod: ``helixrod demo | sweep | fit | force-extension | tweezer-fit |
stability``.

`app` is the typer application (the ``helixrod`` entry point, ``python -m helixrod.cli``).
Its callback turns on float64 (``jax_enable_x64``) once, before any command runs: every
command computes and prints in float64; and, unless ``--no-cache``, the persistent
compilation cache (`helixrod.enable_compilation_cache`), so that a second run of a command
loads its compiled programs instead of compiling them again.  One private module per
command (`_demo`, `_sweep`, `_fit`, `_force_extension`, `_tweezer_fit`, `_stability`); `_numbers` parses
every number spec (comma-separated lists and ``start:stop:num`` grid axes), `_paths`
checks input and output files before anything runs, `_report` prints the tables of a fit;
figures are drawn only by the plotting module (`helixrod.plot`).
"""

from __future__ import annotations

import typer
import typer.core

from ._demo import demo as demo, demo_dna_fit as demo_dna_fit, demo_fit as demo_fit
from ._fit import example_data_path as example_data_path, fit as fit
from ._force_extension import force_extension_command as force_extension_command
from ._report import print_fit as print_fit
from ._stability import stability_command as stability_command
from ._sweep import sweep_command as sweep_command
from ._tweezer_fit import tweezer_fit_command as tweezer_fit_command



def _plain_help_flag(command_class):
    """`command_class` whose --help row shows no value: typer prints a flag's type
    (`<bool>`) unless its metavar is empty, and the help option is click's own."""

    class Command(command_class):
        def get_help_option(self, ctx):
            option = super().get_help_option(ctx)
            if option is not None:
                option.metavar = ""
            return option

    Command.__name__ = command_class.__name__
    return Command


_Command = _plain_help_flag(typer.core.TyperCommand)
app = typer.Typer(
    add_completion=False, help="helixrod: elastic Kirchhoff rods and helices in JAX.",
    cls=_plain_help_flag(typer.core.TyperGroup),
)


@app.callback()
def _main(
    cache: bool = typer.Option(
        True, "--cache/--no-cache", envvar="HELIXROD_CACHE",
        metavar="", help="keep compiled programs on disk for later runs ($HELIXROD_CACHE_DIR, default ~/.cache/helixrod/jax; "
        "safe to delete); HELIXROD_CACHE=0 turns the default off",
    ),
) -> None:
    """helixrod command line."""
    import jax

    jax.config.update("jax_enable_x64", True)
    if cache:
        from .._cache import enable_compilation_cache

        try:
            enable_compilation_cache()
        except (OSError, ValueError) as error:  # an unwritable cache slows a run, never stops it
            typer.echo(f"warning: no compilation cache ({error})", err=True)


app.command(cls=_Command)(demo)
app.command(name="sweep", cls=_Command)(sweep_command)
app.command(cls=_Command)(fit)
app.command(name="force-extension", cls=_Command)(force_extension_command)
app.command(name="tweezer-fit", cls=_Command)(tweezer_fit_command)
app.command(name="stability", cls=_Command)(stability_command)
