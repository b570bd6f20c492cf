"""The parameter map of the RCO estimator: Theta = T eta.

theta (n_u, n_phi) is flattened row-major into Theta, whose entry e = i * n_phi + j is theta[i, j]. Each entry
is either pinned to zero or equal to one parameter of the vector eta (n_params,), so that Theta = T eta with
T a 0/1 matrix (n_entries, n_params) with at most one 1 per row:

* a mask pins entries (their rows of T are zero);
* tie labels let entries share one parameter (entries with the same label hold the same parameter; a negative
  label pins the entry).

Parameters are numbered in the order their first entry appears in Theta, so that the first entry that holds
parameter p (its representative) rises with p. Without mask and tie, T is the identity.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ..blocks.base import DEFAULT_DTYPE
from ..errors import ConfigError, DimensionError


class ParameterMap(nn.Module):
    """Which parameter each entry of theta holds: Theta = T eta, built from a mask and tie labels.

    The index arrays are buffers (they move with the estimator that holds the map) and are not saved in a
    ``state_dict``: they follow from ``mask`` and ``tie``.

    Parameters
    ----------
    n_u : int
        Rows of theta (the width of u).
    phi_names : Sequence[str]
        One name per column of theta (the entries of phi); their number is n_phi.
    mask : array_like of bool, optional
        (n_u, n_phi), True where the entry is a parameter; False pins it to zero. All True by default.
    tie : array_like of int, optional
        (n_u, n_phi) integer labels: entries with the same label share one parameter; a negative label pins the
        entry to zero. By default every entry has its own label.
    block : str, optional
        The name of the block the map belongs to, for error messages.
    dtype : torch.dtype, optional
        Floating-point type of ``tie_matrix``.

    Attributes
    ----------
    n_entries : int
        n_u * n_phi, the length of Theta.
    n_params : int
        The number of parameters, the length of eta (n_theta of the estimator).
    unpinned : torch.Tensor
        Bool (n_u, n_phi): True where the entry holds a parameter, False where it is pinned to zero.
    param_of_entry : torch.Tensor
        Int64 (n_entries,): entry e of Theta -> the parameter it holds, -1 where it is pinned.
    unpinned_entries : torch.Tensor
        Int64 (n_unpinned,): the entries of Theta that hold a parameter, ascending.
    param_of_unpinned : torch.Tensor
        Int64 (n_unpinned,): the parameter held by each of ``unpinned_entries``.
    entry_of_param : torch.Tensor
        Int64 (n_params,): parameter p -> its representative, the first entry of Theta that holds it; so
        eta = Theta[entry_of_param].
    tie_matrix : torch.Tensor or None
        T (n_entries, n_params), T[e, p] = 1 where entry e holds parameter p; None unless ``shared`` (then
        T is a selection, applied by indexing).
    shared : bool
        Whether some parameter is held by more than one entry.
    identity : bool
        Whether every entry is its own parameter (T = I: no entry pinned, none shared).
    names : list[str]
        One name per parameter: the names of the entries that hold it, joined by ' = ' (an entry's name is
        its column's, prefixed with 'i:' for row i when n_u > 1).

    Raises
    ------
    DimensionError
        If ``mask`` or ``tie`` is not (n_u, n_phi).
    ConfigError
        If ``tie`` does not hold integers, or no entry is left free.
    """

    def __init__(self, n_u: int, phi_names: Sequence[str], mask=None, tie=None, block: str = "identified",
                 dtype: torch.dtype = DEFAULT_DTYPE):
        super().__init__()
        phi_names = list(phi_names)
        self.block = block
        shape = (n_u, len(phi_names))
        mask = torch.ones(shape, dtype=torch.bool) if mask is None else torch.as_tensor(mask, device="cpu")
        if tuple(mask.shape) != shape:
            raise DimensionError(f"block '{block}': mask has shape {tuple(mask.shape)}, expected "
                                 f"(n_u, n_phi) = {shape} for phi = {phi_names}")
        labels = torch.arange(mask.numel()).reshape(shape) if tie is None else torch.as_tensor(tie, device="cpu")
        if tuple(labels.shape) != shape:
            raise DimensionError(f"block '{block}': tie has shape {tuple(labels.shape)}, expected "
                                 f"(n_u, n_phi) = {shape} for phi = {phi_names}")
        if labels.is_floating_point() or labels.dtype == torch.bool:
            raise ConfigError(f"block '{block}': tie must hold integer labels, got dtype {labels.dtype}")
        unpinned = mask.bool() & (labels >= 0)
        # Parameters numbered by first appearance of their label in Theta.
        param_of_entry, number = [], {}
        for holds, label in zip(unpinned.flatten().tolist(), labels.flatten().tolist()):
            param_of_entry.append(number.setdefault(label, len(number)) if holds else -1)
        self.n_entries, self.n_params = len(param_of_entry), len(number)
        if self.n_params == 0:
            raise ConfigError(f"block '{block}': the mask leaves no free entry of theta")
        param_of = torch.tensor(param_of_entry, dtype=torch.int64)
        unpinned_entries = torch.nonzero(param_of >= 0).flatten()
        self.register_buffer("unpinned", unpinned, persistent=False)
        self.register_buffer("param_of_entry", param_of, persistent=False)
        self.register_buffer("unpinned_entries", unpinned_entries, persistent=False)
        self.register_buffer("param_of_unpinned", param_of[unpinned_entries], persistent=False)
        self.register_buffer("entry_of_param", torch.tensor(
            [param_of_entry.index(p) for p in range(self.n_params)], dtype=torch.int64), persistent=False)
        self.shared = self.n_params < unpinned_entries.numel()
        self.identity = bool(unpinned.all()) and not self.shared
        tie_matrix = None
        if self.shared:
            tie_matrix = torch.zeros(self.n_entries, self.n_params, dtype=dtype)
            tie_matrix[unpinned_entries, param_of[unpinned_entries]] = 1.0
        self.register_buffer("tie_matrix", tie_matrix, persistent=False)
        entry = [f"{i}:{phi_names[j]}" if n_u > 1 else phi_names[j] for i in range(n_u) for j in range(shape[1])]
        self.names = [" = ".join(entry[e] for e in range(self.n_entries) if param_of_entry[e] == p)
                      for p in range(self.n_params)]

    def eta_of(self, theta_flat: torch.Tensor) -> torch.Tensor:
        """The parameters eta read from Theta at their representatives: eta = Theta[entry_of_param].

        Parameters
        ----------
        theta_flat : torch.Tensor
            Theta, (B, n_entries).

        Returns
        -------
        torch.Tensor
            (B, n_params), a new tensor.
        """
        return theta_flat.index_select(1, self.entry_of_param)

    def regressor_of_eta(self, psi_t: torch.Tensor) -> torch.Tensor:
        """The regressor of eta from that of Theta: Psi_eta^T = Psi^T T.

        Parameters
        ----------
        psi_t : torch.Tensor
            Psi^T over Theta, (B, n_z, n_entries).

        Returns
        -------
        torch.Tensor
            (B, n_z, n_params); ``psi_t`` itself where T is the identity.
        """
        if self.shared:
            return psi_t @ self.tie_matrix
        if not self.identity:
            return psi_t.index_select(2, self.entry_of_param)
        return psi_t

    def write_theta_(self, theta_flat: torch.Tensor, eta: torch.Tensor) -> None:
        """Write Theta = T eta into ``theta_flat`` in place; pinned entries are left as they are.

        Parameters
        ----------
        theta_flat : torch.Tensor
            Theta, (B, n_entries), written in place.
        eta : torch.Tensor
            (B, n_params).
        """
        if self.shared:
            # Theta[e] = eta[param_of_entry[e]] for every unpinned entry e
            theta_flat.index_copy_(1, self.unpinned_entries, eta.index_select(1, self.param_of_unpinned))
        else:
            # Theta[entry_of_param[p]] = eta[p]
            theta_flat.index_copy_(1, self.entry_of_param, eta)

    def check_shared(self, what: str, values: torch.Tensor) -> None:
        """Check that entries holding the same parameter are given the same value.

        Parameters
        ----------
        what : str
            What the values are (``'theta0'``, ``'theta_bounds low'``), for the error message.
        values : torch.Tensor
            (B, n_entries), laid out like Theta.

        Raises
        ------
        ConfigError
            If two entries that share a parameter have different values.
        """
        if not self.shared:
            return
        at_representative = values[:, self.entry_of_param[self.param_of_unpinned]]
        if not bool((values[:, self.unpinned_entries] == at_representative).all()):
            raise ConfigError(f"block '{self.block}': {what} differs between entries of theta that share a "
                              "parameter (tie)")

    def extra_repr(self) -> str:
        return f"n_entries={self.n_entries}, n_params={self.n_params}, shared={self.shared}"
