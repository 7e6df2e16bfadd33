"""The valid ranges of the command-line options that are not config keys, by command, and the
checks of the options that are not numbers (`--execution`, `--key-map`).

Options that set a config key (`sefa reflow --samples`, `sefa align --eps`, `sefa train
training.lr=...`) are checked by the range the config states beside the key (sefa_data/ranges.py,
through pipelines/workspace.py:check_new_flags). Both run before a command reads data or writes a
file, and name the option as it was typed.
"""

from __future__ import annotations

from typing import Any, Sequence

from sefa_data.errors import ConfigError, SefaInputError
from sefa_data.ranges import POSITIVE, SEED, Range, count

STEPS = count(1, 100_000)  # a fixed-step solver's or the diffusion sampler's steps

OPTIONS: dict[str, dict[str, Range]] = {
    "eval": {
        "--n-test": count(1, 1_000_000),
        "--start-seed": SEED,
        "--max-steps": count(1, 100_000_000),
        "--steps": STEPS,
        "--windows": count(1),
        "--samples": count(2, 10_000),  # the spread of one sample is 0 by definition
    },
    # the execution's options (sefa eval --env, sefa serve, sefa choose-execution) are the
    # ranges ExecutionSettings states beside its fields (sefa_model/policy/execution.py)
    "choose": {
        "--n-val": count(1, 1_000_000),
        "--val-start-seed": SEED,
        "--max-steps": count(1, 100_000_000),
        "--steps": STEPS,
        "--budget-ms": POSITIVE,
        "--fps": POSITIVE,
        "--min-gain-se": Range(lo=0, hi=100),
    },
    # --opset: sefa_deploy/export.py:OPSETS (below 18 the exporter cannot lower Mish)
    # --tolerance: a fraction of the action's range (sefa_deploy/export.py:ARTIFACT_TOLERANCE)
    "export": {"--steps": STEPS, "--fps": POSITIVE, "--opset": count(18, 21),
               "--tolerance": Range(lo=0, hi=1, lo_open=True, hi_open=True)},
    "serve": {
        "--port": count(0, 65535),  # 0 picks a free port
        "--steps": STEPS,
        "--seed": SEED,
        "--max-message-mb": POSITIVE,
        "--max-queue": count(0),
        "--request-timeout": POSITIVE,
        "--fps": POSITIVE,
    },
}


def check_options(command: str, values: dict[str, Any]) -> None:
    """Each given value (None: not given) against its option's range; the first one out of
    range is a ConfigError naming the option."""
    ranges = OPTIONS[command]
    for name, value in values.items():
        ranges[name].check(value, name)


def check_choice(name: str, value: str, choices: Sequence[str]) -> None:
    """A value that must be one of a few names; ConfigError naming the option otherwise."""
    if value not in choices:
        raise ConfigError(f"not one of {', '.join(choices)}: {value!r}", key=name)


def key_map_option(items: list[str] | None,
                   names: str = "an openpi observation name") -> dict[str, str]:
    """--key-map's NAME=KEY items (sefa_deploy/server.py:parse_key_map) -> {NAME: KEY, or "" to
    drop NAME}; a bad item is a SefaInputError naming the option. `names` says what a NAME is
    (`sefa eval`'s are a simulator's)."""
    from sefa_deploy.server import parse_key_map

    try:
        return parse_key_map(items or [])
    except ValueError as e:
        raise SefaInputError(str(e).replace("an openpi observation name", names),
                             key="--key-map") from None


def execution_option(mode: str | None, replan_every: int | None = None,
                     samples: int | None = None, decay: float | None = None,
                     ensemble_k: float | None = None, weak: str | None = None):
    """The `--execution` options as ExecutionSettings, or None when none was given (the
    policy's recorded execution, else the default, applies). Values are checked against the
    settings' ranges, the error naming the option; checks that need the policy's
    n_action_steps come once it is loaded (`ExecutionSettings.resolved`)."""
    from sefa_model.policy.execution import ExecutionSettings

    given = {"mode": mode, "replan_every": replan_every, "samples": samples, "decay": decay,
             "ensemble_k": ensemble_k, "weak": weak}
    given = {k: v for k, v in given.items() if v is not None}
    if not given:
        return None
    settings = ExecutionSettings(**given)
    settings.check(100_000)  # ranges and combinations; n_action_steps is known later
    return settings


def export_execution(mode: str | None, replan_every: int | None, samples: int | None,
                     decay: float | None, ensemble_k: float | None, carrier: str):
    """`sefa export`'s --execution options (None: none given). bid is refused first: it needs a
    second, weaker policy (--weak), which `carrier` (an export, a LeRobot policy folder) does
    not hold."""
    if mode == "bid":
        raise SefaInputError(f"bid contrasts the policy with a weaker one, which {carrier} does "
                             "not carry: use receding, ensemble or coherent (or serve with "
                             "--execution bid --weak CHECKPOINT@SOLVER-STEPS)", key="--execution")
    return execution_option(mode, replan_every, samples, decay, ensemble_k)


def check_serving(meta: dict, key_map: dict[str, str]) -> None:
    """`sefa serve`'s options against the policy once it is loaded (its metadata): --key-map's
    keys among its observations."""
    from sefa_deploy.server import check_key_map

    try:
        check_key_map(key_map, meta)
    except ValueError as e:
        raise SefaInputError(str(e), key="--key-map") from None
