"""The algorithm registry (isodream_rl/trainers/registry.py): ``algo.name -> builder``, filled where each
algorithm is defined."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from isodream_rl.trainers.components import RunComponents
from isodream_rl.trainers.config import ALGO_NAMES, ConfigError
from isodream_rl.trainers.isodream import IsoDreamComponents
from isodream_rl.trainers.isodream_v2 import IsoDreamV2Components
from isodream_rl.trainers.learners import ISODREAM_ALGOS
from isodream_rl.trainers.registry import ALGORITHMS, components_builder, register_algorithm

ROOT = Path(__file__).resolve().parents[1]


def test_the_baselines_register_themselves_when_imported():
    from isodream_rl.baselines import TorchRLDreamerComponents, TorchRLDreamerV3Components

    assert components_builder("torchrl_dreamer") is TorchRLDreamerComponents
    assert components_builder("torchrl_dreamer_v3") is TorchRLDreamerV3Components
    assert set(ALGO_NAMES) <= set(ALGORITHMS)
    # the DreamerV2-style variants, and a name of the user's own (informational: the algo fields set the variant)
    assert components_builder("dreamerv2") is components_builder("my_variant") is IsoDreamV2Components


def test_the_default_and_its_ablations_are_dreamer_v3s_learner_and_isodream_v2_the_dreamerv2_style_one():
    assert ISODREAM_ALGOS == (
        "isodream",
        "isodream_no_inverse",
        "isodream_no_attention",
        "isodream_no_static",
    )
    for name in ISODREAM_ALGOS:
        assert components_builder(name) is IsoDreamComponents, name
    for name in ("isodream_v2", "isodream_paper", "dreamerv2"):
        assert components_builder(name) is IsoDreamV2Components, name


def test_the_former_name_of_the_default_is_refused_naming_the_new_one():
    with pytest.raises(ConfigError, match=r"algo=isodream_v3 is now algo=isodream \(.*algo=isodream_v2\)"):
        components_builder("isodream_v3")


def test_a_name_is_registered_once():
    @register_algorithm("test_registry_algo")
    class Mine(RunComponents):
        pass

    try:
        assert components_builder("test_registry_algo") is Mine
        # the same builder again: nothing changes
        assert register_algorithm("test_registry_algo")(Mine) is Mine
        with pytest.raises(ValueError, match="registered already"):
            register_algorithm("test_registry_algo")(RunComponents)
    finally:
        del ALGORITHMS["test_registry_algo"]


def test_a_baseline_not_imported_yet_is_a_config_error_naming_its_module():
    code = (
        "from isodream_rl.trainers.config import ConfigError\n"
        "from isodream_rl.trainers.registry import components_builder\n"
        "try:\n"
        "    components_builder('torchrl_dreamer')\n"
        "except ConfigError as err:\n"
        "    print(err)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "algo.name='torchrl_dreamer'" in out.stdout and "isodream_rl.baselines" in out.stdout
