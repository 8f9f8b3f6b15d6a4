"""orientlab: a live sensor-fusion lab in the browser (see README.md and docs/architecture.md).

A regular package, not a namespace one: two checkouts on one path never merge into one
``app`` (a module missing from one would be taken from the other)."""
