"""TorchRL-style configurable keys for the competency modules (private).

TorchRL's losses name their tensordict keys in an ``_AcceptedKeys`` dataclass and let users
rename them with ``set_keys``; the metric modules and the assessor follow the same contract as
:class:`~tensordict.nn.TensorDictModuleBase` subclasses (they are metrics, not losses).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key


class KeyedModule(TensorDictModuleBase):
    """A module whose keys live in ``_AcceptedKeys``; ``in_keys`` / ``out_keys`` follow them.

    Subclasses define ``_AcceptedKeys`` (a dataclass of keys with defaults) and list which of
    its fields are inputs and outputs in ``_inputs`` and ``_outputs``.
    """

    _AcceptedKeys: ClassVar[type]
    _inputs: ClassVar[tuple[str, ...]] = ()
    _outputs: ClassVar[tuple[str, ...]] = ()

    def __init__(self) -> None:
        super().__init__()
        self._tensor_keys = self._AcceptedKeys()
        self._sync_keys()

    @property
    def default_keys(self) -> Any:
        """The default keys (a fresh ``_AcceptedKeys``)."""
        return self._AcceptedKeys()

    @property
    def tensor_keys(self) -> Any:
        """The keys in use."""
        return self._tensor_keys

    def set_keys(self, **kwargs: NestedKey | None) -> KeyedModule:
        """Rename keys (``None`` restores a default); returns the module.

        Raises:
            ValueError: a name that is not one of the module's keys.
        """
        fields = {f.name for f in dataclasses.fields(self._AcceptedKeys)}
        for name, value in kwargs.items():
            if name not in fields:
                raise ValueError(
                    f"{name}: not a key of {type(self).__name__}; its keys are {sorted(fields)}"
                )
            default = getattr(self._AcceptedKeys(), name)
            setattr(self._tensor_keys, name, default if value is None else unravel_key(value))
        self._sync_keys()
        return self

    def _sync_keys(self) -> None:
        self.in_keys = [getattr(self._tensor_keys, name) for name in self._inputs]
        self.out_keys = [getattr(self._tensor_keys, name) for name in self._outputs]
