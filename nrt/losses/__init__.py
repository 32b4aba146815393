"""The objectives of stage 2, one per module, each a pure loss function of fields and sample
tensors and a unit (:class:`~nrt.losses.objective.Objective`: a name, a weight schedule and
the loss on a stage's samples) that the stages hold and loop over:
:mod:`~nrt.losses.rte` (residual of the radiative transfer equation),
:mod:`~nrt.losses.boundary` (inflow condition), :mod:`~nrt.losses.observation` (photos at
the box exit), :mod:`~nrt.losses.vre` (volume rendering of the photos), and the split
formulation's :mod:`~nrt.losses.photo` and :mod:`~nrt.losses.transport`; plus where they
look (:mod:`~nrt.losses.samplers`). The paper formulation's losses are in units of the light
field's ``radiance_scale`` squared."""
