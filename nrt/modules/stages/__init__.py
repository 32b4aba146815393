"""The stages ``nrt-train stage=<name>`` trains (LightningModules on the written contract of
:mod:`~nrt.modules.stages.stage`), their schedules, and how they receive components."""
