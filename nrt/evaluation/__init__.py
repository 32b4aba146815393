"""Evaluation of trained media: export, Mitsuba re-renders, metrics, reports."""
