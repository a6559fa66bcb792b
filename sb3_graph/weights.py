"""Backward-compatible home of :mod:`sb3_graph.files.policy_files`.

User code and plugins register their policy classes for policy files here
(``sb3_graph.weights.register_policy``, :data:`POLICY_REGISTRY`) and read files with
``read_policy_tensors`` / ``load_policy``: these names keep working. ``POLICY_REGISTRY`` is the
same dictionary object as the new module's, so a registration through either name counts.
"""

from sb3_graph.files.policy_files import (
    FORMAT,
    METADATA_KEY,
    POLICY_REGISTRY,
    SUFFIX,
    VERSION,
    LoadedPolicy,
    PolicyDescription,
    PolicyFileError,
    describe_policy,
    init_from_file,
    load_policy,
    load_policy_tensors,
    read_policy_tensors,
    read_sb3_zip,
    read_weights_file,
    register_policy,
    registered_policy,
    resize_graph_policy,
    save_policy,
)

__all__ = [
    "FORMAT",
    "METADATA_KEY",
    "POLICY_REGISTRY",
    "SUFFIX",
    "VERSION",
    "LoadedPolicy",
    "PolicyDescription",
    "PolicyFileError",
    "describe_policy",
    "init_from_file",
    "load_policy",
    "load_policy_tensors",
    "read_policy_tensors",
    "read_sb3_zip",
    "read_weights_file",
    "register_policy",
    "registered_policy",
    "resize_graph_policy",
    "save_policy",
]
