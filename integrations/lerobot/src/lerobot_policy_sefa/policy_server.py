"""LeRobot's async policy server, serving sefa policies too:

    python -m lerobot_policy_sefa.policy_server --host=127.0.0.1 --port=8080 --fps=10

LeRobot's `policy_server` accepts only the policy types in its own list
(`lerobot.async_inference.constants.SUPPORTED_POLICIES`) and never imports plugins. This
launcher imports the plugin (registering the type), appends "sefa" to that list (the very list
object the server module imported, so its check sees it), and runs LeRobot's unchanged
`serve()` with the same command line. LeRobot's own `robot_client` then drives a sefa policy:

    python -m lerobot.async_inference.robot_client --policy_type=sefa \\
        --pretrained_name_or_path=DIR --server_address=127.0.0.1:8080 --robot.type=... \\
        --actions_per_chunk=8

The server calls `predict_action_chunk` with one observation at a time; the policy keeps the
last n_obs_steps of them as its frame history, so with n_obs_steps > 1 the history is the
observations the server chose to run, which the client sends at its own pace (the server
skips ones too similar to the last).
"""

from __future__ import annotations

import lerobot_policy_sefa
from lerobot.async_inference import constants, policy_server
from sefa_deploy.lerobot_format import POLICY_TYPE


def register() -> None:
    """Let LeRobot's policy server accept sefa policies."""
    if "SefaConfig" not in lerobot_policy_sefa.__all__:
        raise SystemExit(1)  # the plugin printed why (a LeRobot outside the tested versions)
    if policy_server.SUPPORTED_POLICIES is not constants.SUPPORTED_POLICIES:
        raise SystemExit("lerobot_policy_sefa.policy_server: this LeRobot's policy_server keeps "
                         "its own list of policy types; the launcher cannot add 'sefa' to it")
    if POLICY_TYPE not in constants.SUPPORTED_POLICIES:
        constants.SUPPORTED_POLICIES.append(POLICY_TYPE)


def main() -> None:
    register()
    policy_server.serve()


if __name__ == "__main__":
    main()
