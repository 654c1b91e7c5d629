"""Whether the stations of a file share one instrument: a score test, station by station, of the instrument's own
errors the closed loop found.

The closed loop fits one instrument for every station of a file (:mod:`torchcal.diagnose.candidates`: a station
column records where the one tracker stood). Where two trackers measured one file, or the tracker was serviced
between placements, its errors differ from station to station, and the fit over all stations is their blend. The
data say so: for each instrument effect of the final model and each station ``s``, the alternative "station ``s``
reads with an error of its own of the same form" adds the effect's columns restricted to that station's rows; its
score test at the final fit (the part of those columns orthogonal to the fit's span, which holds every station's
pose and the shared effect: :mod:`torchcal.diagnose.score`'s legend) is chi-square with the effect's ``k`` degrees of
freedom where the stations share one instrument. The ``K`` stations' tests of each effect are corrected together
(Bonferroni over effects x stations). A significant one is named, not acted on: which stations go together is for the
user to say (a file per instrument calibrates each apart).
"""

from __future__ import annotations

import torch

from torchcal import _dual
from torchcal.effects import Context, MeasurementModel
from torchcal.estimate.lm import LMResult
from torchcal.stats import chi2_sf_log10

Tensor = torch.Tensor


def effect_columns(model: MeasurementModel, index: int, ctx: Context, p: Tensor, W: Tensor) -> Tensor:
    """Whitened Jacobian ``(3N, k)`` of the predictions with respect to the parameters of ``model.effects[index]`` at
    their current values."""
    eff = model.effects[index]
    named = [(n, v) for n, v in eff.named_parameters()]
    keys = [f"effects.{index}.{n}" for n, _ in named]
    shapes, sizes = [v.shape for _, v in named], [v.numel() for _, v in named]

    def fun(theta: Tensor) -> Tensor:
        params = {k: v.reshape(s) for k, v, s in zip(keys, torch.split(theta, sizes), shapes)}
        pred = torch.func.functional_call(model, params, (ctx,))
        return (W @ _dual.sub(pred, p).unsqueeze(-1)).reshape(-1)  # torchcal._dual: p is constant

    theta0 = torch.cat([v.detach().reshape(-1) for _, v in named])
    return torch.func.jacfwd(fun)(theta0).detach()


def station_consistency(
    model: MeasurementModel, result: LMResult, ctx: Context, p: Tensor, W: Tensor, station_names, *, alpha: float
) -> list[dict]:
    """The score test of every instrument effect of ``model`` at every station (module docstring).

    Args:
        result: the final fit of ``model`` to ``p`` (whitened residuals and Jacobian at its solution).
        ctx, p, W: its samples (``ctx.station`` the station of each row), measured points ``(N, 3)`` and whitening.
        station_names: the stations' names, by index.
        alpha: the family-wise level a station's corrected p is compared with.

    Returns:
        One dict per effect and station: ``effect``, ``station``, ``statistic``, ``dof``, ``p_value``,
        ``p_bonferroni``, ``differs``; empty with fewer than two stations or no instrument effect.
    """
    inst = [i for i, e in enumerate(model.effects) if e.kind == "instrument"]
    if ctx.station is None or not inst:
        return []
    stations = sorted(int(s) for s in torch.unique(ctx.station).tolist())
    if len(stations) < 2:
        return []
    r, J = result.residuals, result.jacobian
    n_obs = 3 * ctx.q.shape[0]
    Q, _ = torch.linalg.qr(J / J.norm(dim=0).clamp(min=1e-300))
    s0sq = result.sigma0_sq
    rows = ctx.station.repeat_interleave(3)
    tests = len(inst) * len(stations)
    out = []
    for i in inst:
        C = effect_columns(model, i, ctx, p, W)
        for s in stations:
            Cs = torch.zeros(len(r), C.shape[1], dtype=C.dtype, device=C.device)
            Cs[:n_obs] = C * (rows == s).unsqueeze(-1)
            Cs = Cs / Cs.norm(dim=0).clamp(min=1e-300)
            for _ in range(2):  # projected twice for round-off
                Cs = Cs - Q @ (Q.T @ Cs)
            Qc, Rc = torch.linalg.qr(Cs)
            keep = Rc.diagonal().abs() > 1e-6
            k = int(keep.sum())
            stat = float((Qc[:, keep].T @ r).square().sum()) / s0sq if k and s0sq > 0 else 0.0
            pv = chi2_sf_log10(stat, k)[0] if k else 1.0
            name = station_names[s] if s < len(station_names) else str(s)
            pb = min(1.0, tests * pv)
            out.append(
                {
                    "effect": model.effects[i].label(),
                    "station": name,
                    "statistic": stat,
                    "dof": k,
                    "p_value": pv,
                    "p_bonferroni": pb,
                    "differs": pb < alpha,
                }
            )
    return out
