"""Renderers: pixels of view rays from fields (emission-absorption, the volume rendering
equation, the light field at the box exit); objectives and validation share them."""
