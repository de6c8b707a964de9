"""Networks and policies as TensorDict modules, usable in any TorchRL project."""

from rlpipe.modules.exploration import epsilon_greedy
from rlpipe.modules.qnetworks import make_qvalue_actor

__all__ = ["epsilon_greedy", "make_qvalue_actor"]
