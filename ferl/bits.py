"""Binary codes of integers: how a factored action (Sallans & Hinton 2004) is both an index, as
every environment takes actions, and the states of K binary action nodes, as the actor sees it.
Index i ↔ the K bits of i, most significant first."""

import torch


def to_bits(i: torch.Tensor, n_bits: int) -> torch.Tensor:
    """Integer tensor (…) → its binary codes (…, n_bits) as floats, most significant bit first."""
    shifts = torch.arange(n_bits - 1, -1, -1, device=i.device)
    return ((i.unsqueeze(-1) >> shifts) & 1).float()


def from_bits(bits: torch.Tensor) -> torch.Tensor:
    """Binary codes (…, n_bits) → the integers (…) they code (the inverse of ``to_bits``)."""
    # shifts, not 2 ** k: inductor's C++ wrapper has no integer power of a scalar (a compiled
    # Gibbs chain ends here)
    shifts = torch.arange(bits.shape[-1] - 1, -1, -1, device=bits.device)
    return (bits.long() << shifts).sum(-1)
