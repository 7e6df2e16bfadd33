"""What is installed: `sefa --version` and `sefa info` (versions for bug reports)."""

from __future__ import annotations

import json

import typer

from sefa_cli.params import JsonFlag


def print_version(value: bool) -> None:
    """`sefa --version` (an eager option of the root app, cli/main.py)."""
    if value:
        from importlib.metadata import PackageNotFoundError, version

        try:
            print(f"sefa {version('sefa')}")
        except PackageNotFoundError:
            print("sefa (not installed: running from a checkout)")
        raise typer.Exit()


def info(as_json: JsonFlag = False) -> None:
    """Versions of sefa and its libraries, for bug reports."""
    import platform

    from sefa_data.store.zarr_store import package_versions

    data = {"python": platform.python_version(), "platform": platform.platform(),
            **package_versions()}
    try:
        import torch

        data["cuda"] = torch.cuda.is_available()
    except ImportError:
        pass
    print(json.dumps(data, indent=2) if as_json else "\n".join(f"{k}: {v}" for k, v in data.items()))
