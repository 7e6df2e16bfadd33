"""The presets: the settings files shipped with sefa (pipelines/*.yaml, installed with the wheel
as package data of sefa_pipelines), each named by a short name that works from any folder.

A name is a pipeline file's stem (`lerobot_camera_cpu`: lerobot_camera_cpu.yaml) or a train
config's without its `_train` (`lift_lowdim`: lift_lowdim_train.yaml). `sefa run --preset NAME`
runs the pipeline; `sefa train --preset NAME` trains the base flow the pipeline names in its
`train_config` (a preset's pipelines add nothing to it: their `train:` lists are empty), or the
train config of that name. Each file says what it is for in its `# preset:` line, which
`sefa presets` lists.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from sefa_data.config_io import load_yaml
from sefa_data.errors import SefaInputError

HERE = Path(__file__).resolve().parent
ABOUT = "# preset:"  # the line of a preset file that says what it is for


@dataclass(frozen=True)
class Preset:
    name: str
    about: str  # what it is for, in a line
    pipeline: Path | None  # `sefa run --preset NAME`
    train_config: Path | None  # `sefa train --preset NAME`


def _about(path: Path) -> str:
    for line in path.read_text().splitlines():
        if line.startswith(ABOUT):
            return line[len(ABOUT):].strip()
    return ""


def _is_pipeline(data: dict) -> bool:
    """A pipeline file holds stage settings (train_config, reflow, ...); a train config holds
    a policy's (policy, training, shape_meta)."""
    from dataclasses import fields

    from sefa_pipelines.stages import PipelineConfig

    return bool(data) and set(data) <= {f.name for f in fields(PipelineConfig)}


def presets() -> dict[str, Preset]:
    """Every preset by name, in name order."""
    pipelines, trains = {}, {}
    for path in sorted(HERE.glob("*.yaml")):
        data = load_yaml(path) or {}
        if _is_pipeline(data):
            pipelines[path.stem] = (path, data)
        else:
            trains[path.stem.replace("_train", "", 1)] = path
    out = {}
    for name, (path, data) in pipelines.items():
        config = data.get("train_config")
        train = (path.parent / config).resolve() if config else trains.get(name)
        out[name] = Preset(name, _about(path), path, train)
    for name, path in trains.items():
        if name not in out:
            out[name] = Preset(name, _about(path), None, path)
    return dict(sorted(out.items()))


def resolve(name: str, command: str) -> Path:
    """The file `sefa COMMAND --preset NAME` uses: the pipeline (run) or the train config
    (train)."""
    known = presets()
    preset = known.get(name.removesuffix(".yaml"))
    if preset is None:
        raise SefaInputError(f"no preset {name!r} (presets: {', '.join(known)}; `sefa presets` "
                             "says what each is for)", key="--preset")
    path = preset.pipeline if command == "run" else preset.train_config
    if path is None:
        raise SefaInputError(f"{name!r} is a train config, not a pipeline: `sefa train --preset "
                             f"{name}` trains with it (the pipelines: "
                             f"{', '.join(n for n, p in known.items() if p.pipeline)})",
                             key="--preset")
    return path


def missing_file_hint(path: Path) -> str:
    """For a settings file that does not exist: the preset of that file name, if one is
    installed (`sefa train pipelines/NAME_train.yaml` outside a sefa checkout)."""
    for p in presets().values():
        for command, file in (("train", p.train_config), ("run", p.pipeline)):
            if file is not None and file.name == Path(path).name:
                return f"; the installed preset of that name: `sefa {command} --preset {p.name}`"
    return ""
