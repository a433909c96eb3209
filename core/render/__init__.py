"""The forward path: scenarios of a reconstruction rendered by the PBR pass (:mod:`core.render.scenario`)."""
