"""A kind's package whose import fails: a dependency it names is not what it expects."""

raise ImportError("cannot import name 'Blade' from 'sawlib'")
