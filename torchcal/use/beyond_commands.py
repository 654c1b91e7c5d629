"""A compensation beyond the calibrated region: the rows a run gives to another model solved again with it, the
targets a file asks for, and how far to trust each command (``torchcal compensate``'s rows, for library users)."""

from __future__ import annotations

import torch


def targets_of_file(data, six_d: bool):
    """``(model, rows) -> (positions, orientations or None)`` of a targets file, in the instrument frame of ``model``
    (the run at the rows' station and probe): the file's ``x,y,z`` (``rx,ry,rz``), or what a program's joints mean."""
    from torchcal.robot import transforms as tf
    from torchcal.use.compensate import program_orientations, program_targets

    def targets_of(at, rows):
        p = data.p[rows] if data.p is not None else program_targets(at, data.q[rows])
        if not six_d:
            return p, None
        return p, tf.so3_exp(data.r[rows]) if data.r is not None else program_orientations(at, data.q[rows])

    return targets_of


def resolver(res, station, probe, targets_of, context, weight):
    """``(geometric, rows) ->`` those rows of ``res`` solved again, in place, with the run's kinematic calibration
    ``geometric`` in each row's own station's frame with its own probe."""
    from torchcal.use.compensate import solve_rows_with
    from torchcal.use.rundir import at_station

    def resolve(geometric, rows):
        robot, n = geometric.robot, len(res.q)
        for s, p in sorted(set(zip(station[rows].tolist(), probe[rows].tolist(), strict=True))):
            sel = rows[(station[rows] == s) & (probe[rows] == p)]
            names = (robot.stations[s] if robot.stations else None, robot.probes[p] if robot.probes else None)
            geo, *_ = at_station(geometric, *names)
            pos, rot = targets_of(geo, sel)
            targets = torch.zeros(n, 3, dtype=pos.dtype, device=pos.device)
            targets[sel] = pos
            kw = {"orientation_weight": weight}
            if rot is not None:  # full-length, as the rows' context: solve_rows_with takes the rows of both
                kw["orientations"] = torch.eye(3, dtype=rot.dtype, device=rot.device).repeat(n, 1, 1)
                kw["orientations"][sel] = rot
            solve_rows_with(geo, res, sel, targets, context=context, **kw)

    return resolve


def commanded_trust(run_dir, model, meta, res, ctx, plain, resolve):
    """A compensation's ``sx, sy, sz`` and ``model`` per row (an index into :data:`torchcal.use.rundir.MODEL_NAMES`;
    ``plain`` marks the rows commanded without the learned parts): rows beyond the region that the run gives to another
    model (the one it chose there, or its kinematic calibration where the model's sigma is far above that one's:
    :func:`torchcal.use.rundir.row_trust`) are solved again with it (``resolve(other, rows)``, in place in ``res``),
    with its sigma at the new commands; rows beyond that the run's model commands without its learned parts say
    ``physical``."""
    from dataclasses import replace

    from torchcal.use.rundir import row_trust

    rt = row_trust(run_dir, model, meta, ctx)
    which = torch.where(plain.cpu(), 2, 0)
    if rt.geometric is None or not bool(rt.which.any()):
        return rt.sigma, which
    rows = torch.nonzero(rt.which).flatten()
    resolve(rt.geometric, rows.to(res.q.device))
    sigma = rt.sigma.clone()
    sub = ctx.subset(rows.to(ctx.q.device))
    sigma[rows] = rt.geometric_sigma(replace(sub, q=res.q[rows.to(res.q.device)]))  # at the new commands
    which[rows] = rt.which[rows]
    return sigma, which
