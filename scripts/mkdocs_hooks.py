"""MkDocs hook (mkdocs.yml `hooks:`): the reference pages are written from the code before
every build, so the site's command and settings reference is the code's."""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def on_pre_build(config, **kwargs) -> None:
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    sys.path.insert(0, str(REPO / "scripts"))
    try:
        import gen_reference
    finally:
        sys.path.remove(str(REPO / "scripts"))
    gen_reference.write()
