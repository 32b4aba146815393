"""The stages ``nrt-train stage=<name>`` trains (LightningModules on the written contract of
:mod:`~nrt.stages.stage`), their components, where they start (:mod:`~nrt.stages.start`),
their schedules and their checkpoint format; the layer above the objectives
(:mod:`nrt.losses`)."""
