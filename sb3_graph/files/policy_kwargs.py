"""One check of a policy's constructor keyword arguments, wherever they come from.

``policy_kwargs`` reach a policy from four places: an SB3 ``model.zip`` (its ``data`` JSON), the
header of a ``.safetensors`` policy file, an experiment YAML (and its ``config.yml`` copy in a run
folder) and ``--hyperparams`` on the command line. All four come from someone else, so before a
policy is built :func:`check_policy_kwargs` checks, by key:

- types and bounds: widths are integers in ``[1, MAX_WIDTH]``, at most ``MAX_LAYERS`` of them;
  counts, flags and numbers have their own ranges (:data:`RULES`); ``aggregation`` and ``pooling``
  are names from the graph layers;
- classes: ``activation_fn`` is one of the element-wise activation modules of
  :data:`ACTIVATIONS` (not any ``torch.nn.Module``), ``optimizer_class`` one of
  :data:`OPTIMIZERS`, whose ``optimizer_kwargs`` are tried on one tensor first (torch refuses
  ``fused`` with ``foreach`` there, not half-way into training);
- size: an estimate of the memory that the networks, their target copies and the optimizer's
  state take, refused above :data:`MAX_POLICY_BYTES`;

and :func:`check_finite_weights` refuses weights with ``NaN`` or infinite values. A key that is not
listed passes only as a plain scalar (the policy's constructor then names it if it is unknown).
"""

from __future__ import annotations

import math
from typing import Any

import torch as th
from torch import nn

from sb3_graph.files.safe_values import check_structure, finite_number

#: widest layer (vertex encoder, convolution or MLP layer) accepted
MAX_WIDTH = 4096
#: most layers in ``conv_dims`` or one ``net_arch`` list
MAX_LAYERS = 32
#: largest estimated memory of a policy: weights, target networks and two optimizer moments (float32)
MAX_POLICY_BYTES = 2 << 30
#: longest string value of a key that is not listed in :data:`RULES`
MAX_STRING = 200
#: element-wise activations that a policy file or an experiment may name
ACTIVATIONS: tuple[type[nn.Module], ...] = (
    nn.ReLU, nn.ReLU6, nn.LeakyReLU, nn.PReLU, nn.RReLU, nn.ELU, nn.SELU, nn.CELU, nn.GELU, nn.SiLU, nn.Mish,
    nn.Tanh, nn.Sigmoid, nn.Hardtanh, nn.Hardswish, nn.Hardsigmoid, nn.Softplus, nn.Softsign, nn.Tanhshrink,
    nn.LogSigmoid, nn.Identity,
)  # fmt: skip
#: optimizers that a policy file or an experiment may name
OPTIMIZERS: tuple[type[th.optim.Optimizer], ...] = (
    th.optim.Adam, th.optim.AdamW, th.optim.SGD, th.optim.RMSprop, th.optim.Adagrad, th.optim.Adadelta,
    th.optim.Adamax, th.optim.NAdam, th.optim.RAdam,
)  # fmt: skip
# Sizes assumed for the memory estimate when the observation space is not known yet.
DEFAULT_NODE_FEATURES = 16
DEFAULT_RELATIONS = 8


class PolicyKwargsError(ValueError):
    """A ``policy_kwargs`` value outside what :func:`check_policy_kwargs` accepts (names the key)."""


def _is_int(value: Any) -> bool:
    return finite_number(value) and float(value).is_integer()


def _integer(low: int, high: int) -> tuple[Any, str]:
    return (lambda v: _is_int(v) and low <= v <= high), f"an integer in [{low}, {high}]"


def _number(low: float, high: float, low_open: bool = False) -> tuple[Any, str]:
    def check(value: Any) -> bool:
        return finite_number(value) and (value > low if low_open else value >= low) and value <= high

    return check, f"a number in {'(' if low_open else '['}{low:g}, {high:g}]"


def _boolean() -> tuple[Any, str]:
    return (lambda v: isinstance(v, bool)), "true or false"


def _widths(value: Any) -> bool:
    return (
        isinstance(value, (list, tuple))
        and 1 <= len(value) <= MAX_LAYERS
        and all(_is_int(d) and 1 <= d <= MAX_WIDTH for d in value)
    )


def _net_arch(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, dict):
        return set(value) <= {"pi", "vf", "qf"} and all(_widths(v) or v == [] for v in value.values())
    return _widths(value) or value == []


def _one_of(options: tuple[Any, ...]) -> tuple[Any, str]:
    return (lambda v: isinstance(v, str) and v in options), f"one of {list(options)}"


def _scalars(value: Any) -> bool:
    return value is None or (
        isinstance(value, dict)
        and all(isinstance(k, str) and _plain(v) for k, v in value.items())
    )


def _plain(value: Any) -> bool:
    """A plain scalar: ``None``, a bool, a bounded finite number, a short string."""
    if value is None or isinstance(value, bool):
        return True
    if isinstance(value, str):
        return len(value) <= MAX_STRING
    return finite_number(value) and abs(value) <= 1e12


def _rules() -> dict[str, tuple[Any, str]]:
    from sb3_graph.common.layers import AGGREGATIONS
    from sb3_graph.common.networks import POOLINGS

    return {
        "encoder_dim": _integer(1, MAX_WIDTH),
        "conv_dims": (_widths, f"a list of 1 to {MAX_LAYERS} integers in [1, {MAX_WIDTH}]"),
        "net_arch": (_net_arch, f"null, a list of 1 to {MAX_LAYERS} integers in [1, {MAX_WIDTH}] or a dict of them"),
        "aggregation": _one_of(tuple(AGGREGATIONS)),
        "pooling": _one_of(tuple(POOLINGS)),
        "n_critics": _integer(1, 32),
        "n_quantiles": _integer(1, 1024),
        "edge_dim": _integer(0, MAX_WIDTH),
        "log_std_init": _number(-20.0, 20.0),
        "clip_mean": _number(0.0, 1000.0, low_open=True),
        "batch_norm_eps": _number(0.0, 1.0, low_open=True),
        "batch_norm_momentum": _number(0.0, 1.0),
        "renorm_warmup_steps": _integer(0, 10**9),
        "features_extractor_kwargs": (_scalars, "null or a mapping of plain values"),
        **{
            key: _boolean()
            for key in (
                "normalize_images", "share_features_extractor", "use_edge_features", "use_sde", "use_expln",
                "ortho_init", "share_trunk", "squash_output", "batch_norm", "full_std",
            )
        },
    }  # fmt: skip


def check_policy_kwargs(
    kwargs: Any,
    source: str = "policy_kwargs",
    observation_space: Any = None,
) -> dict[str, Any]:
    """Check a policy's constructor keyword arguments (see the module docstring).

    :param kwargs: the keyword arguments (classes already resolved, e.g. by
        :func:`sb3_graph.files.safe_values.resolve_name`)
    :param source: what they came from, the start of each message (``policy_kwargs``, a file)
    :param observation_space: the graph space the policy is built for (sizes of the memory
        estimate); ``None``: :data:`DEFAULT_NODE_FEATURES` and :data:`DEFAULT_RELATIONS`
    :return: the keyword arguments, whole floats of integer keys turned into ints
    :raises PolicyKwargsError: ``<source>.<key> must be <allowed>, got <value>``
    """
    if kwargs is None:
        return {}
    if not isinstance(kwargs, dict) or not all(isinstance(key, str) for key in kwargs):
        raise PolicyKwargsError(f"{source} must be a mapping of option names, got {_short(kwargs)}")
    try:
        check_structure(kwargs, source, max_depth=8, max_items=10_000)
    except ValueError as error:
        raise PolicyKwargsError(str(error)) from None
    rules = _rules()
    checked = {}
    for key, value in kwargs.items():
        where = f"{source}.{key}"
        if key == "activation_fn":
            _check_class(value, ACTIVATIONS, where, "an activation")
        elif key == "optimizer_class":
            _check_class(value, OPTIMIZERS, where, "an optimizer")
        elif key == "optimizer_kwargs":
            _check_optimizer_kwargs(value, kwargs.get("optimizer_class", th.optim.Adam), where)
        elif key == "features_extractor_class":
            _check_extractor(value, where)
        elif key in rules:
            check, allowed = rules[key]
            if not check(value):
                raise PolicyKwargsError(f"{where} must be {allowed}, got {_short(value)}")
            value = _ints(key, value)
        elif not _plain(value):
            raise PolicyKwargsError(f"{where}: an option unknown here must be a plain value, got {_short(value)}")
        checked[key] = value
    estimate = estimate_policy_bytes(checked, observation_space)
    if estimate > MAX_POLICY_BYTES:
        raise PolicyKwargsError(
            f"{source}: the networks would take about {estimate / 2**30:.3g} GiB (weights, targets and optimizer "
            f"state), more than the {MAX_POLICY_BYTES / 2**30:g} GiB accepted; make encoder_dim, conv_dims or "
            "n_critics smaller"
        )
    return checked


def _ints(key: str, value: Any) -> Any:
    if key in ("encoder_dim", "n_critics", "n_quantiles", "edge_dim", "renorm_warmup_steps"):
        return int(value)
    if key == "conv_dims":
        return type(value)(int(d) for d in value)
    return value


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _check_class(value: Any, allowed: tuple[type, ...], where: str, what: str) -> None:
    if not isinstance(value, type) or value not in allowed:
        shown = f"{value.__module__}.{value.__qualname__}" if isinstance(value, type) else _short(value)
        raise PolicyKwargsError(f"{where} must be {what} of: {', '.join(c.__name__ for c in allowed)}; got {shown}")


def _check_optimizer_kwargs(value: Any, optimizer_class: Any, where: str) -> None:
    if value is None:
        return
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise PolicyKwargsError(f"{where} must be a mapping of option names, got {_short(value)}")
    for key, item in value.items():
        items = item if isinstance(item, (list, tuple)) else [item]
        if key in ("params", "lr") or len(items) > 8 or not all(_plain(x) and not isinstance(x, str) for x in items):
            raise PolicyKwargsError(
                f"{where}.{key} must be a number, a flag or a short list of numbers (not params or lr), "
                f"got {_short(item)}"
            )
    if optimizer_class not in OPTIMIZERS:
        return  # refused by name under optimizer_class
    probe = nn.Parameter(th.zeros(1))
    try:
        optimizer_class([probe], lr=1e-3, **value)
    except (TypeError, ValueError, RuntimeError) as error:
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise PolicyKwargsError(f"{where}: {optimizer_class.__name__} refuses them: {first}") from None


def _check_extractor(value: Any, where: str) -> None:
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor

    if not isinstance(value, type) or not (
        value is FlattenExtractor
        or (issubclass(value, BaseFeaturesExtractor) and value.__module__.startswith("sb3_graph."))
    ):
        raise PolicyKwargsError(f"{where} must be FlattenExtractor or a features extractor of sb3_graph, "
                                f"got {_short(value)}")  # fmt: skip


def _graph_sizes(observation_space: Any) -> tuple[int, int]:
    node_features = getattr(observation_space, "node_features", None)
    relations = getattr(observation_space, "num_relations", None)
    if not isinstance(node_features, int) or not isinstance(relations, int):
        return DEFAULT_NODE_FEATURES, DEFAULT_RELATIONS
    return max(node_features, 1), max(relations, 1)


def estimate_policy_bytes(kwargs: dict[str, Any], observation_space: Any = None) -> int:
    """Bytes that a graph policy built with ``kwargs`` takes, roughly: one trunk per network (the
    actor and ``n_critics`` critics), each with a target copy and two optimizer moments, float32.

    :param kwargs: checked keyword arguments (defaults of :class:`sb3_graph.GraphPolicy` for missing ones)
    :param observation_space: the graph space (vertex features and relations), or ``None``
    :return: the estimate in bytes
    """
    node_features, relations = _graph_sizes(observation_space)
    encoder = int(kwargs.get("encoder_dim", 64))
    convs = [int(d) for d in kwargs.get("conv_dims", (64, 64))]
    edge = int(kwargs.get("edge_dim", 0))
    parameters = node_features * encoder + encoder
    width = encoder
    for out in convs:
        parameters += (relations + 1) * width * out + relations * edge * out + out
        width = out
    arch = kwargs.get("net_arch")
    layers = [width, *(arch if isinstance(arch, list) else [w for v in (arch or {}).values() for w in v])]
    parameters += sum(a * b for a, b in zip(layers, layers[1:]))
    parameters += layers[-1] * int(kwargs.get("n_quantiles", 2))
    networks = 1 + int(kwargs.get("n_critics", 2))
    return int(math.ceil(parameters * networks * 4 * 4))


def check_finite_weights(tensors: Any, source: str) -> None:
    """Refuse weights holding ``NaN`` or infinite values (they would fail a run half-way).

    :param tensors: a state dict (name -> tensor) or an ``nn.Module``
    :param source: the file, for messages
    :raises PolicyKwargsError: naming the first such tensor
    """
    items = tensors.state_dict().items() if isinstance(tensors, nn.Module) else tensors.items()
    for name, tensor in items:
        if isinstance(tensor, th.Tensor) and tensor.is_floating_point() and not bool(th.isfinite(tensor).all()):
            raise PolicyKwargsError(f"{source}: weight {name!r} holds NaN or infinite values")
