"""The model file: an ETAR model as the JSON object of docs/model-format.md.

``ETAR.to_dict``, ``from_dict``, ``save`` and ``load`` call these.  They read a model
only through its attributes and build one only through the class they are given, so
the format (its fields, its checks, its error wording) changes here without the model.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

FORMAT_NAME = "etar-model"
FORMAT_VERSION = 1


def model_to_dict(model) -> dict:
    """The model file's object of ``model`` (its parameters checked first)."""
    model._checked_parameters()
    hyper = dict(
        n_restarts=model.n_restarts, init_iter=model.init_iter, solver=model.solver, w_steps=model.w_steps,
        w_l2=model.w_l2, sigma_prior_weight=model.sigma_prior_weight,
        sigma_prior_scale=model.sigma_prior_scale, ab_prior=model.ab_prior, window=model.window,
    )
    out = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "transitions": model.transitions,
        "n_phases": model.n_phases,
        "n_state": model.n_state,
        "n_force": model.n_force,
        "hyperparameters": hyper,
        "parameters": {
            "A": np.asarray(model.A).tolist(),
            "B": np.asarray(model.B).tolist(),
            "Sigma": np.asarray(model.Sigma).tolist(),
            "W": np.asarray(model.W).tolist(),
            "goal": None if model.goal is None else np.asarray(model.goal).tolist(),
        },
    }
    if model.fit_report_ is not None:
        r = model.fit_report_
        out["fit"] = dict(log_likelihood=r.log_likelihood, objective=r.objective, n_iter=r.n_iter,
                          converged=r.converged, n_samples=r.n_samples, seconds=r.seconds, seed=r.seed)
    if model.metadata:
        out["metadata"] = model.metadata
    return out


def write_model_file(path, data: dict) -> None:
    """Write a model file's object as JSON (floats round-trip bit for bit)."""
    Path(path).write_text(json.dumps(data, indent=1) + "\n")


def model_from_dict(cls, data: dict, source: str):
    """An instance of ``cls`` (``ETAR``) from a model file's object; a ``ValueError``
    names ``source`` and the field."""

    def need(key, where=data, prefix=""):
        if key not in where:
            raise ValueError(f"{source}: field '{prefix}{key}' is missing")
        return where[key]

    if data.get("format") != FORMAT_NAME:
        raise ValueError(f"{source}: field 'format' is {data.get('format')!r}, expected {FORMAT_NAME!r}")
    if need("version") != FORMAT_VERSION:
        raise ValueError(f"{source}: field 'version' is {data['version']!r}; this library reads {FORMAT_VERSION}")
    try:
        model = cls(need("n_phases"), need("transitions"), **data.get("hyperparameters", {}))
    except TypeError as exc:  # an unknown hyperparameter
        raise ValueError(f"{source}: field 'hyperparameters': {exc}") from None
    except ValueError as exc:  # a bad value: the message names its key
        raise ValueError(f"{source}: {exc}") from None
    params = need("parameters")
    for key in ("A", "B", "Sigma", "W"):
        try:
            setattr(model, key, np.array(need(key, params, "parameters."), dtype=np.float64))
        except (TypeError, ValueError, OverflowError) as exc:  # JSON's integers have no bound
            raise ValueError(f"{source}: field 'parameters.{key}' is not a numeric array ({exc})") from None
    goal = params.get("goal")
    try:
        model.goal = None if goal is None else np.array(goal, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{source}: field 'parameters.goal' is not a numeric array ({exc})") from None
    metadata = data.get("metadata", {})
    if not isinstance(metadata, dict):
        raise ValueError(f"{source}: field 'metadata' must be a JSON object, got {json.dumps(metadata)[:80]}")
    model.metadata = dict(metadata)
    try:
        _, Sigma, _, _ = model._checked_parameters()
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}") from None
    # the header must describe the arrays, and every covariance must be one
    for key, actual in (("n_state", model.n_state), ("n_force", model.n_force)):
        if key in data and data[key] != actual:
            raise ValueError(f"{source}: field '{key}' is {data[key]!r}, but the parameters have {actual}")
    for j, S in enumerate(Sigma):
        if not np.allclose(S, S.T, rtol=1e-9, atol=1e-12):
            raise ValueError(f"{source}: field 'parameters.Sigma[{j}]' is not symmetric")
        try:
            np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            raise ValueError(f"{source}: field 'parameters.Sigma[{j}]' is not positive definite "
                             f"(eigenvalues {np.round(np.linalg.eigvalsh(S), 12).tolist()})") from None
    return model


def read_model_file(path: Path) -> dict:
    """The JSON object of a model file; a ``ValueError`` names ``path`` and what is wrong."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such model file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the model file ({exc})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a JSON model file ({exc})") from None
    except RecursionError:  # the parser's own bound on nesting
        raise ValueError(f"{path}: not a JSON model file (nested too deeply)") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object (an etar-model file), got a {type(data).__name__}")
    return data
