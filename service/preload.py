"""What the workers' fork server loads before the first worker forks from it
(:data:`articast.service.worker.WORKER_MODULES`): the tracker's compiled kernels, when
numba's on-disk cache has them (~1 s a worker otherwise spends loading them before its first
frame). A first run has none: its worker compiles them itself and says so."""

from articast.core.faces import kernels as faces_kernels
from articast.core.tracking import kernels

if kernels.compiled_on_disk():
    kernels.warm_up()
    if faces_kernels.compiled_on_disk():
        faces_kernels.warm_up()
elif kernels.compiled_on_disk(kernels.TRACKER):  # a first demo compiled only the tracker's
    kernels.warm_up(kernels.TRACKER)
