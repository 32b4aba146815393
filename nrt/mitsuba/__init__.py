"""Mitsuba 3 in one place: variant choice (:mod:`~nrt.mitsuba.variant`), the ``nrt_hg_grid``
phase plugin (:mod:`~nrt.mitsuba.hg_grid_phase`), scene descriptions
(:mod:`~nrt.mitsuba.scene`), plain and differentiable rendering (:mod:`~nrt.mitsuba.render`)
and export (:mod:`~nrt.mitsuba.export`). Mitsuba itself is imported only inside functions,
after :func:`~nrt.mitsuba.variant.select_variant` chose the variant."""
