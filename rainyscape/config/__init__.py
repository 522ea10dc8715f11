"""Pipeline configuration: typed dataclasses, ``key=value`` overrides, plain-YAML files.

- :mod:`~rainyscape.config.schema`: the dataclasses, value coercion and :func:`materialize`,
  the one gate from a method's plain-data recipe to typed component configs;
- :mod:`~rainyscape.config.overrides`: ``key=value`` overrides and method lookup;
- :mod:`~rainyscape.config.yaml_io`: ``config.yml`` (plain data) round trips.

A method's recipe (:class:`MethodSpec`) holds component options as plain dicts so method
modules import nothing heavy; :func:`method_config` and :func:`load_yaml` return configs
whose options are the components' typed ``Config`` dataclasses, and everything after them
sees only that form. Nothing here imports torch.
"""

from rainyscape.config.overrides import (apply_overrides, describe_tree, method_config, method_spec,
                                         parse_overrides)
from rainyscape.config.schema import (ComponentConfig, LossConfig, MethodSpec, PhaseConfig,
                                      PipelineConfig, TrainerConfig, coerce, describe_run_length,
                                      materialize, run_length, with_run_length)
from rainyscape.config.yaml_io import from_dict, load_yaml, save_yaml, to_dict

__all__ = [
    "ComponentConfig", "LossConfig", "MethodSpec", "PhaseConfig", "PipelineConfig", "TrainerConfig",
    "apply_overrides", "coerce", "describe_run_length", "describe_tree", "from_dict", "load_yaml", "materialize",
    "method_config", "method_spec", "parse_overrides", "run_length", "save_yaml", "to_dict",
    "with_run_length",
]
