"""The parameter map Theta = T eta from a mask and tie labels, checked against maps worked out by hand."""

import pytest
import torch

import rcotorch as rt
from rcotorch.estimator.parameter_map import ParameterMap


def _tied():
    # Theta row-major: e0 = (0, a) label 7, e1 = (0, b) label -1, e2 = (0, c) label 9,
    #                  e3 = (1, a) label 9, e4 = (1, b) label 7, e5 = (1, c) masked.
    # Labels by first appearance: 7 -> parameter 0, 9 -> parameter 1.
    return ParameterMap(2, ["a", "b", "c"], mask=[[True, True, True], [True, True, False]],
                        tie=[[7, -1, 9], [9, 7, 4]], block="est")


def test_a_tied_and_masked_map_holds_the_entries_worked_out_by_hand():
    pm = _tied()
    assert pm.n_entries == 6 and pm.n_params == 2 and pm.shared and not pm.identity
    assert pm.param_of_entry.tolist() == [0, -1, 1, 1, 0, -1]
    assert pm.unpinned_entries.tolist() == [0, 2, 3, 4] and pm.param_of_unpinned.tolist() == [0, 1, 1, 0]
    assert pm.entry_of_param.tolist() == [0, 2]
    assert pm.unpinned.tolist() == [[True, False, True], [True, True, False]]
    assert pm.names == ["0:a = 1:b", "0:c = 1:a"]
    T = [[1, 0], [0, 0], [0, 1], [0, 1], [1, 0], [0, 0]]
    assert pm.tie_matrix.tolist() == T
    theta = torch.zeros(1, 6, dtype=torch.float64)
    pm.write_theta_(theta, torch.tensor([[2.0, 5.0]], dtype=torch.float64))
    assert theta.tolist() == [[2.0, 0.0, 5.0, 5.0, 2.0, 0.0]]
    assert pm.eta_of(theta).tolist() == [[2.0, 5.0]]
    psi_t = torch.arange(1.0, 7.0, dtype=torch.float64).reshape(1, 1, 6)
    assert pm.regressor_of_eta(psi_t).tolist() == [[[1.0 + 5.0, 3.0 + 4.0]]]       # Psi^T T
    pm.check_shared("theta0", theta)
    with pytest.raises(rt.ConfigError, match="block 'est': theta0 differs between entries of theta that share"):
        pm.check_shared("theta0", torch.tensor([[2.0, 0.0, 5.0, 4.0, 2.0, 0.0]]))


def test_a_masked_map_selects_and_a_plain_map_is_the_identity():
    masked = ParameterMap(1, ["a", "b", "c"], mask=[[True, False, True]])
    assert masked.param_of_entry.tolist() == [0, -1, 1] and masked.entry_of_param.tolist() == [0, 2]
    assert not masked.shared and not masked.identity and masked.tie_matrix is None
    psi_t = torch.tensor([[[1.0, 2.0, 3.0]]])
    assert masked.regressor_of_eta(psi_t).tolist() == [[[1.0, 3.0]]]
    theta = torch.full((1, 3), 9.0)
    masked.write_theta_(theta, torch.tensor([[4.0, 6.0]]))
    assert theta.tolist() == [[4.0, 9.0, 6.0]]                         # a pinned entry is left as it is
    plain = ParameterMap(2, ["a", "b"])
    assert plain.identity and plain.n_params == 4 and plain.entry_of_param.tolist() == [0, 1, 2, 3]
    assert plain.regressor_of_eta(psi_t) is psi_t
    assert plain.names == ["0:a", "0:b", "1:a", "1:b"]


def test_bad_masks_and_ties_name_the_block_and_the_setting():
    with pytest.raises(rt.DimensionError, match=r"block 'est': mask has shape \(1, 2\), expected \(n_u, n_phi\) = "
                                                r"\(2, 3\)"):
        ParameterMap(2, ["a", "b", "c"], mask=[[True, False]], block="est")
    with pytest.raises(rt.DimensionError, match=r"block 'est': tie has shape \(3,\)"):
        ParameterMap(2, ["a", "b", "c"], tie=[0, 1, 2], block="est")
    with pytest.raises(rt.ConfigError, match="block 'est': tie must hold integer labels"):
        ParameterMap(1, ["a"], tie=[[True]], block="est")
    with pytest.raises(rt.ConfigError, match="block 'est': the mask leaves no free entry"):
        ParameterMap(1, ["a", "b"], mask=[[True, False]], tie=[[-1, 0]], block="est")


def test_the_estimator_holds_its_map_which_moves_with_it_and_is_not_saved():
    est = rt.RCOEstimator({"y0": 2}, nc=2, p0=100.0, tie=[[0, 1, 0, 1, 2, 3]])
    pm = est.parameter_map
    assert est.n_theta == pm.n_params == 4 and est.theta_names == pm.names
    assert est.param_of is pm.param_of_entry and est.free_idx is pm.entry_of_param
    assert not est.all_free
    assert not any(key.startswith("parameter_map") for key in est.state_dict())
    est.to(torch.float32)
    assert est.parameter_map.tie_matrix.dtype == torch.float32 and est.param_of.dtype == torch.int64
