"""One sweep module per stage (``cadalign bench STAGE``): each ``*_sweep(data, cfg)`` returns a
:class:`~cadalign.bench.framework.Sweep` of the stage's knobs; knob lists grow with the size level (tiny 0, small 1,
full 2). The registry (:mod:`cadalign.bench.registry`) names them."""
