"""Export of property grids as Mitsuba files: ``.vol`` grids and a ``medium.xml`` scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nrt.mitsuba.scene import mitsuba_properties


def write_medium_files(mi, folder: str | Path, grids: dict, bbox, effects: dict) -> dict[str, str]:
    """Export property grids for Mitsuba: ``sigma_t.vol``, ``albedo.vol`` (and ``g.vol``
    when g varies) in Mitsuba's binary grid format, and ``medium.xml``, a scene holding the
    medium box (load it with ``mi.load_file`` or ``<include>`` it; a g grid needs the
    ``nrt_hg_grid`` plugin, registered by :func:`select_variant`)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    props = mitsuba_properties(grids, effects)
    files = {}
    for key, value in props.items():
        if isinstance(value, np.ndarray):
            files[key] = folder / f"{key}.vol"
            mi.VolumeGrid(np.ascontiguousarray(value, np.float32)).write(str(files[key]))
    lo, hi = (np.asarray(b, float) for b in np.asarray(bbox))
    box = (f'<transform name="to_world"><scale value="{_xyz(hi - lo)}"/>'
           f'<translate value="{_xyz(lo)}"/></transform>')
    cube = (f'<transform name="to_world"><scale value="{_xyz((hi - lo) / 2)}"/>'
            f'<translate value="{_xyz((hi + lo) / 2)}"/></transform>')

    def volume(name: str) -> str:
        return (f'<volume type="gridvolume" name="{name}"><string name="filename" '
                f'value="{files[name].name}"/>{box}</volume>')
    phase = effects["phase"]
    if phase == "isotropic":
        phase_xml = '<phase type="isotropic"/>'
    elif phase == "hg":
        phase_xml = f'<phase type="hg"><float name="g" value="{props["g"]:.6f}"/></phase>'
    else:
        phase_xml = f'<phase type="nrt_hg_grid">{volume("g")}</phase>'
    xml = (f'<scene version="3.0.0">\n  <!-- nrt export: medium box {lo.tolist()} .. '
           f'{hi.tolist()} -->\n  <shape type="cube" id="medium_box">\n    {cube}\n'
           '    <bsdf type="null"/>\n    <medium type="heterogeneous" name="interior">\n'
           f'      {volume("sigma_t")}\n      {volume("albedo")}\n'
           f'      <float name="scale" value="1"/>\n      {phase_xml}\n    </medium>\n'
           '  </shape>\n</scene>\n')
    files["xml"] = folder / "medium.xml"
    files["xml"].write_text(xml)
    return {k: str(v) for k, v in files.items()}


def _xyz(v) -> str:
    return ", ".join(f"{float(x):.9g}" for x in v)
