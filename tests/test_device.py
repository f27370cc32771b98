"""Where tensors live: the replay stays on the CPU, and every tensor an update, the acting policy or the open-loop
prediction hands a model is on the model's device first, for every algorithm ``isodream-train`` runs.

Without a GPU, the model sits on PyTorch's ``meta`` device, where the replay never is: a forward pre-hook on every
module records the devices of the tensors handed to the first module called and stops the computation there
(``meta`` tensors hold no values to compute on). The cases marked ``cuda`` run ``bench/gpu_check.py``'s checks (tiny
runs of every algorithm and mode with ``train.device=cuda``) where a GPU exists, and are skipped elsewhere.
"""

import json

import pytest
import torch
from tensordict import TensorDictBase
from torch import nn

from isodream_rl.run_utils.checkpoint import rng_state, set_rng_state
from isodream_rl.trainers import ConfigError
from isodream_rl.trainers.openloop import open_loop_prediction
from isodream_rl.trainers.registry import make_components
from isodream_rl.trainers.run import evaluate_checkpoint
from isodream_rl.video_prediction.trainer import VideoTrainConfig
from tests.conftest import load_bench
from tests.test_trainer import replay_batch

GPU_CHECK = load_bench("gpu_check")
ALGOS = GPU_CHECK.registered_algos()
META = torch.device("meta")
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="checks a machine without a CUDA GPU")


class _FirstCall(Exception):
    """Raised by the pre-hook at the first module call, once its inputs are recorded."""


def _tensors(value):
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, TensorDictBase):
        yield from value.values(include_nested=True, leaves_only=True)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _tensors(item)
    elif isinstance(value, dict):
        for item in value.values():
            yield from _tensors(item)


def first_call(modules, call) -> tuple[str, set[torch.device]]:
    """The first of ``modules`` (or of their submodules) that ``call()`` calls, and the devices of the tensors it
    was handed."""
    seen = {}

    def record(module, args, kwargs):
        seen.update(module=type(module).__name__, devices={t.device for t in _tensors((args, kwargs))})
        raise _FirstCall

    hooked = {id(m): m for root in modules for m in root.modules()}
    handles = [m.register_forward_pre_hook(record, with_kwargs=True) for m in hooked.values()]
    try:
        with pytest.raises(_FirstCall):
            call()
    finally:
        for handle in handles:
            handle.remove()
    return seen["module"], seen["devices"]


def components_of(algo: str, tmp_path):
    cfg = GPU_CHECK.composed(f"algo={algo}", "size=tiny", f"run_dir={tmp_path}")
    cfg.train.batch_size, cfg.train.sequence_length = 2, 6
    return make_components(cfg, action_dim=2, scratch_dir=tmp_path / "scratch")


@pytest.mark.parametrize("algo", ALGOS)
def test_an_update_hands_the_model_the_replay_sample_on_the_models_device(algo, tmp_path):
    components = components_of(algo, tmp_path)
    stepper = components.stepper
    stepper.model_loss.to(META)  # the world model, on a device the replay sample is not on
    sample = replay_batch()
    assert {t.device.type for t in _tensors(sample)} == {"cpu"}
    held = [v for v in vars(stepper).values() if isinstance(v, nn.Module)]
    module, devices = first_call([*components.modules().values(), *held], lambda: stepper.step(None, sample))
    assert devices == {META}, f"{algo}: {module} was handed tensors on {devices}"


@pytest.mark.parametrize("algo", ALGOS)
def test_the_open_loop_prediction_hands_the_world_model_the_window_on_its_device(algo, tmp_path):
    world_model = components_of(algo, tmp_path).world_model
    if world_model is None:
        pytest.skip(f"algo={algo} has no open-loop prediction (no Iso-Dream world model)")
    world_model.to(META)
    window = replay_batch().reshape(2, 6)
    module, devices = first_call([world_model], lambda: open_loop_prediction(world_model, window, context=3))
    assert devices == {META}, f"{algo}: {module} was handed tensors on {devices}"


@pytest.mark.parametrize("algo", ALGOS)
def test_the_acting_policy_hands_its_models_the_observation_on_their_device(algo, tmp_path):
    policy = components_of(algo, tmp_path).behavior.policy
    observation = (
        policy.make_tensordict_primer().primers.zero()
    )  # the carried state, as an env's reset gives it
    observation.update(
        {"pixels": torch.zeros(3, 64, 64, dtype=torch.uint8), "is_init": torch.ones(1, dtype=torch.bool)}
    )
    policy.to(META)
    # the policy itself reads the env's tensordict where it is; the models it calls get it on their device
    module, devices = first_call(list(policy.children()), lambda: policy(observation))
    assert devices == {META}, f"{algo}: {module} was handed tensors on {devices}"


def test_random_states_of_gpus_this_machine_lacks_leave_its_own():
    state = rng_state()
    expected = torch.rand(3)
    # a checkpoint of a run on more GPUs than this machine has (none, on a CPU-only one)
    state["cuda"] = [torch.zeros(16, dtype=torch.uint8)] * (torch.cuda.device_count() + 1)
    set_rng_state(state)
    assert torch.equal(torch.rand(3), expected)


@no_cuda
def test_a_missing_gpu_is_one_line_for_evaluation_and_video(tmp_path):
    message = "--device='cuda' but this machine has no usable CUDA GPU: set --device=cpu"
    with pytest.raises(ConfigError, match=message):
        evaluate_checkpoint(tmp_path, device="cuda")
    with pytest.raises(ValueError, match="device='cuda' but this machine has no usable CUDA GPU"):
        VideoTrainConfig(device="cuda")


@no_cuda
def test_the_gpu_benches_stop_in_one_line_without_a_gpu(capsys):
    with pytest.raises(SystemExit, match="bench/gpu_check.py needs a CUDA GPU"):
        GPU_CHECK.main(["--json", "/nonexistent/gpu_check.json"])
    with pytest.raises(SystemExit) as stopped:
        load_bench("update_speed").main(["--device", "cuda"])
    assert stopped.value.code == 2 and "no usable CUDA GPU: set --device=cpu" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------ on a CUDA GPU
@cuda
@pytest.mark.parametrize("algo", ALGOS)
def test_every_algorithm_trains_evaluates_and_resumes_on_the_gpu_and_on_a_cpu_only_machine(algo, tmp_path):
    found = GPU_CHECK.check_rl(algo, tmp_path, device="cuda")
    assert found["updates"] > 0
    continued = GPU_CHECK.check_cpu_only([tmp_path / f"rl_{algo}"], device="cuda", timeout=600)
    assert continued[f"rl_{algo}"]["updates_back_on_device"] > found["updates"]


@cuda
@pytest.mark.parametrize("algo", ALGOS)
def test_the_world_model_mode_trains_probes_and_resumes_on_the_gpu(algo, tmp_path):
    found = GPU_CHECK.check_world_model(algo, tmp_path, device="cuda")
    if "skipped" in found:
        pytest.skip(found["skipped"])
    continued = GPU_CHECK.check_cpu_only([tmp_path / f"world_model_{algo}"], device="cuda", timeout=600)
    assert continued[f"world_model_{algo}"]["updates_back_on_device"] > found["updates"]


@cuda
def test_the_decomposition_bench_runs_on_the_gpu(tmp_path):
    assert set(GPU_CHECK.check_decomposition(tmp_path, device="cuda")) == {"isodream", "isodream_v2"}


@cuda
def test_the_video_predictor_trains_on_the_gpu_and_evaluates_there_and_on_the_cpu(tmp_path):
    assert set(GPU_CHECK.check_video(tmp_path, device="cuda")["psnr_3"]) == {"cuda", "cpu"}


@cuda
def test_update_speed_times_updates_on_the_gpu(tmp_path):
    path = tmp_path / "speed.json"
    out = load_bench("update_speed").main(
        ["--device", "cuda", "--size", "tiny", "--rounds", "2", "--warmup", "1", "--json", str(path)]
    )
    assert json.loads(path.read_text()) == out and out["gpu"] and out["device"] == "cuda"
    for algo, entry in out["algos"].items():
        assert len(entry["update_memory_gb"]) == 2 and entry["max_update_memory_gb"] > 0, algo


@cuda
def test_gpu_check_writes_its_json(tmp_path):
    path = tmp_path / "gpu_check.json"
    args = ["--parts", "update,end_to_end", "--algos", "isodream", "--sizes", "tiny", "--rounds", "2"]
    args += ["--e2e-algos", "isodream", "--e2e-size", "tiny", "--e2e-updates", "40", "--json", str(path)]
    assert GPU_CHECK.main(args) == 0
    saved = json.loads(path.read_text())
    assert saved["ok"] and saved["gpu"] and saved["torch"] == torch.__version__ and saved["commit"]
    assert saved["update"]["tiny"]["isodream"]["median_wall_s"] > 0
    assert saved["end_to_end"]["isodream"]["updates_per_s"] > 0
