"""Command group ``mosaicmap keys``: the map owner's signing keys (:mod:`mapstore.signing`)."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.common import FullHelpGroup, no_config, no_quiet
from pipeline.errors import BadInput


@click.group("keys", cls=FullHelpGroup)
def keys_group() -> None:
    """Signing keys of a map owner (Ed25519)."""


@no_config
@no_quiet
@keys_group.command("new")
@click.argument("out", type=click.Path(dir_okay=False, path_type=Path))
def keys_new_cmd(out: Path) -> None:
    """Write a new key pair: the private key OUT (mode 0600: the map owner keeps it, `export
    --sign OUT`) and the public key OUT.pub (what vehicles trust: `track --key OUT.pub` or
    [tracker.bundle] trusted_keys). Never overwrites a file."""
    from mapstore.signing import write_key_pair

    try:
        priv, pub_path, pub = write_key_pair(out)
    except FileExistsError as e:
        raise BadInput(e.args[0], "exists: refusing to overwrite a key") from None
    except OSError as e:
        raise BadInput(out, f"cannot write the key ({e.strerror})") from None
    click.echo(f"{priv}: private key (keep it secret); {pub_path}: public key {pub.key_id}")
