"""Optimal control: the interior-point NLP solver, the multiple-shooting transcription
(minimum time, energy, fuel and their mixes) and ``minimum_time_reorientation``.

Every public name is re-exported by ``jaxquat`` (use ``jaxquat.name``); the modules here are
the layer's files (``docs/architecture.md`` has the map)."""
