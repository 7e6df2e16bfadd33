"""Print NAME==VERSION, one a line, for every distribution that `sefa[test]` needs (its
requirements' closure, at the versions installed here) and the GPU machines' image lacks, for
scripts/gpu_prepare.sh. The image's list is the device tool's (KINDS.md, "Python packages
already there"); typer is carried although the image has it, for the version sefa runs with,
and PyAV is left out (see LEAVE_OUT)."""

from __future__ import annotations

import re
from importlib.metadata import PackageNotFoundError, distribution

from packaging.requirements import Requirement

IMAGE = """absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs
botorch build certifi charset-normalizer chex click cloudpickle cmake colorama contourpy coverage
cuda-bindings cuda-core cuda-pathfinder cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops
equinox etils execnet filelock flatbuffers flax fonttools formulaic frozenlist fsspec gpytorch
grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna imageio iniconfig
interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver
lazy-loader lightning lightning-utilities linear-operator lineax llvmlite lxml markdown
markdown-it-py markupsafe matplotlib mdurl meson ml-dtypes mpi4py mpmath msgpack multidict
multipledispatch mypy-extensions nanobind narwhals networkx ninja numba numba-cuda numpy numpyro
nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime nvidia-cudnn-cu13
nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13
nvidia-ml-py nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir
onnxruntime onnxscript opencv-python-headless optax opt-einsum opt-einsum-fx optimistix
orbax-checkpoint packaging pandas pathspec patsy peft pillow pip pluggy portalocker
prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments pyparsing
pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock pytest-timeout
pytest-xdist python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu safetensors
scikit-build-core scikit-image scikit-learn scipy seaborn sentencepiece sentence-transformers
setuptools shellingham simplejson six sortedcontainers statsmodels sympy tabulate tensorboard
tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm tokenizers toolz torch
torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm transformers treescope triton
typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel wrapt xarray
xxhash yarl zipp""".split()
CARRY_ANYWAY = {"typer"}
# PyAV (35 MiB, LeRobot's videos) is no part of the GPU checks and would not fit a call's 64 MiB
LEAVE_OUT = {"av"}


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def closure(name: str, extra: str = "", seen: dict | None = None) -> dict[str, str]:
    """{distribution: installed version} of `name` and everything it requires, here."""
    seen = {} if seen is None else seen
    if norm(name) in seen:
        return seen
    try:
        dist = distribution(name)
    except PackageNotFoundError:  # an optional or platform-only requirement not installed here
        return seen
    seen[norm(name)] = dist.version
    for line in dist.requires or []:
        req = Requirement(line)
        if req.marker is None or req.marker.evaluate({"extra": extra, "python_version": "3.12"}):
            closure(req.name, "", seen)
    return seen


if __name__ == "__main__":
    image = {norm(n) for n in IMAGE}
    for name, version in sorted(closure("sefa", "test").items()):
        if name not in {"sefa", *LEAVE_OUT} and (name not in image or name in CARRY_ANYWAY):
            print(f"{name}=={version}")
