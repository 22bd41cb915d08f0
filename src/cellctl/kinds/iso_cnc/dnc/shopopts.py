"""The shop every ``cellctl dnc`` command works on: ``--dir SHOP`` (its dnc.toml) or
``--use-cell`` (the cell's iso-cnc machines)::

    @dnc.command()
    @shop_options
    @click.pass_context
    def status(ctx: click.Context, shop: Path, use_cell: bool) -> None:
        config = shop_config(ctx, shop, use_cell)
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from cellctl.ui.common import cell_dir

if TYPE_CHECKING:
    from cellctl.kinds.iso_cnc.dnc.config import ShopConfig


def shop_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """``--dir SHOP`` and ``--use-cell`` (see module docstring)."""
    f = click.option(
        "--use-cell",
        is_flag=True,
        help="Feed the iso-cnc machines of the cell's cell.toml (--cell) instead of dnc.toml; "
        "the shop directory is then <cell>/shop unless --dir is given.",
    )(f)
    return click.option(
        "--dir",
        "shop",
        envvar="CELLCTL_SHOP",
        default="shop",
        show_default=True,
        type=click.Path(file_okay=False, path_type=Path),
        help="The shop directory: dnc.toml, one directory per machine "
        "(with --use-cell: <cell>/shop).",
    )(f)


def shop_config(ctx: click.Context, shop: Path, use_cell: bool) -> ShopConfig:
    """The shop: ``--dir``'s dnc.toml; with ``--use-cell`` the cell's iso-cnc machines, its
    shop directory ``<cell>/shop`` unless ``--dir`` (or ``$CELLCTL_SHOP``) names another:
    never the unrelated ``./shop`` of wherever the command runs.

    The config says how to name the shop in a command it suggests (``ShopConfig.command``):
    a shop named with ``--dir`` (or ``$CELLCTL_SHOP``) or ``--cell`` by its absolute path, so
    the command works as printed wherever it is run; the default ``./shop`` by nothing."""
    import dataclasses

    from cellctl.kinds.iso_cnc.dnc.config import load_shop

    given = ctx.get_parameter_source("shop") is not click.core.ParameterSource.DEFAULT
    named = ("--dir", str(shop.absolute())) if given else ()
    if not use_cell:
        return dataclasses.replace(load_shop(shop), after=named)
    cell = cell_dir(ctx)
    if not given:
        shop = cell / "shop"
    config = load_shop(shop, cell=cell)
    return dataclasses.replace(
        config, before=("--cell", str(cell.absolute())), after=("--use-cell", *named)
    )
