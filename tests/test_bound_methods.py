"""The registry of error-bound methods (bounds/methods.py): names, capabilities and the messages of its checks."""

import pytest

from robust_imdp.bounds import methods as M
from robust_imdp.errors import InvalidInputError, ProblemFileError

W = "p.toml"


def _msg(f, *a):
    with pytest.raises(InvalidInputError) as e:
        f(*a)
    return type(e.value), str(e.value)


def test_names_and_routes():
    assert M.ERROR_BOUNDS == ("optimal", "ridge", "chowdhury")
    assert [M.get(n).route for n in M.ERROR_BOUNDS] == ["rkhs", "rkhs", "gp"]
    assert M.get("ridge").local_lambda and not M.get("optimal").local_lambda
    assert M.get("chowdhury").gp_posterior and not M.get("chowdhury").refine


@pytest.mark.parametrize("call, kind, want", [
    (lambda: M.get("optimal").check_guarantee("paper"), InvalidInputError,
     "guarantee 'paper' (Thm 1 as printed) needs error_bound 'chowdhury'; got 'optimal'"),
    (lambda: M.get("chowdhury").check_noise_options(0.1, False), InvalidInputError,
     "misspecification and iid_noise apply to error_bound 'optimal' or 'ridge' only; the GP route (error_bound "
     "'chowdhury') has neither; got misspecification=0.1, iid_noise=False"),
    (lambda: M.get("ridge").check_gp_options({"lengthscale": 1, "optimize": True}), InvalidInputError,
     "gp_options ['optimize'] apply only to error_bound 'chowdhury' (a GP posterior); error_bound 'ridge' uses the "
     "unit-amplitude kernel with the given lengthscale only"),
    (lambda: M.get("chowdhury").check_known_parts(["a"], True, 1.0, 2.0), InvalidInputError,
     "error_bound 'chowdhury' (the GP route, bounds.bound_image) bounds f_u + mu jointly for an affine f_u = A x + b "
     "only; modes ['a'] have a nonlinear known part f: use error_bound 'optimal' or 'ridge'"),
    (lambda: M.get("chowdhury").check_known_parts([], False, 1.0, 2.0), InvalidInputError,
     "error_bound 'chowdhury' (the GP route) takes one rkhs_bound, one lengthscale and no known components; per-mode "
     "or per-component values need error_bound 'optimal' or 'ridge'; got rkhs_bound=1.0, lengthscale=2.0"),
    (lambda: M.get("optimal").check_refine(True), InvalidInputError,
     "[refine] needs error_bound 'optimal' or 'ridge' without iid_noise (the bounds of new cells must hold on the "
     "same event); got error_bound='optimal', iid_noise=True"),
    (lambda: M.get("optimal").check_file_options({"bound_tol": 1, "optimize": 1}, W), ProblemFileError,
     W + ": [gp].optimize applies only to error_bound = \"chowdhury\" (a GP posterior); error_bound = \"optimal\" "
     "uses the unit-amplitude kernel with the given lengthscale only: remove the key or set error_bound = "
     "\"chowdhury\""),
    (lambda: M.get("chowdhury").check_file_local_points(W), ProblemFileError,
     W + ": [gp].local_points applies to error_bound = \"optimal\" or \"ridge\" only"),
    (lambda: M.get("chowdhury").check_file_refine(False, W), ProblemFileError,
     W + ": [refine] needs [gp].error_bound = \"optimal\" or \"ridge\" without iid_noise (the bounds of new cells "
     "must hold on the same event as the grid's)"),
    (lambda: M.get("optimol"), InvalidInputError,
     "error_bound must be one of ('optimal', 'ridge', 'chowdhury'); got 'optimol'"),
    (lambda: M.get("optimol", W), ProblemFileError,
     W + ": [gp].error_bound must be one of optimal, ridge, chowdhury; got 'optimol' (did you mean 'optimal'?)"),
    (lambda: M.get(3, W), ProblemFileError, W + ": [gp].error_bound must be one of optimal, ridge, chowdhury; got 3"),
])
def test_messages_are_the_former_ones(call, kind, want):
    with pytest.raises(kind) as e:
        call()
    assert type(e.value) is kind and str(e.value) == want


def test_allowed_options_pass():
    M.get("optimal").check({"guarantee": "confidence", "misspecification": 0.1, "iid_noise": True,
                            "gp_options": {"lengthscale": 1.0}, "nonlinear_modes": ["a"], "uniform": False,
                            "refine": False})
    M.get("chowdhury").check({"guarantee": "paper", "gp_options": {"optimize": True}})
    M.get("ridge").check({"local_points": 5, "lengthscale": 1.0}, where=W)
