"""sefa policies in LeRobot: `SefaConfig` (`--policy.type=sefa`), `SefaPolicy` and
`make_sefa_pre_post_processors`, registered when LeRobot's tools import this package (they import
every installed distribution named `lerobot_policy_*` before parsing --policy.path).

Tested with LeRobot TESTED_LEROBOT. Under another LeRobot the type is not registered and one line
says why (LeRobot's own error, "Policy type 'sefa' ... is not registered", follows); set
LEROBOT_POLICY_SEFA_ANY_LEROBOT=1 to register it anyway.
"""

from __future__ import annotations

import os
import sys
from importlib.metadata import PackageNotFoundError, version

TESTED_LEROBOT = ">=0.6.1,<0.7"  # pyproject.toml pins the same range
ANY_LEROBOT = "LEROBOT_POLICY_SEFA_ANY_LEROBOT"


def lerobot_outside_tested(installed: str | None = None) -> str | None:
    """One line when the installed LeRobot is outside TESTED_LEROBOT, else None."""
    from packaging.specifiers import SpecifierSet

    try:
        installed = installed or version("lerobot")
    except PackageNotFoundError:
        return "lerobot_policy_sefa: LeRobot is not installed (pip install 'lerobot>=0.6.1,<0.7')"
    if SpecifierSet(TESTED_LEROBOT).contains(installed, prereleases=True):
        return None
    return (f"lerobot_policy_sefa: LeRobot {installed} is outside the versions this plugin was "
            f"tested with ({TESTED_LEROBOT}), so the policy type 'sefa' is not registered: "
            f"pip install 'lerobot{TESTED_LEROBOT}', or set {ANY_LEROBOT}=1 to try anyway")


_refusal = lerobot_outside_tested()
if _refusal is not None and not os.environ.get(ANY_LEROBOT):
    print(_refusal, file=sys.stderr)
    __all__: list[str] = []
else:
    from .configuration_sefa import SefaConfig
    from .modeling_sefa import SefaPolicy
    from .processor_sefa import make_sefa_pre_post_processors

    __all__ = ["SefaConfig", "SefaPolicy", "make_sefa_pre_post_processors"]
