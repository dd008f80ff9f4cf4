"""Filtering many recordings, and training several models, as parallel tasks on Ray.

Ray is an optional dependency (``pip install 'torchfilt[distributed]'``); it is imported only when
one of these functions runs, never by ``import torchfilt``.

**Filtering.** :func:`filter_recordings_ray` shards the recordings into batches with the plan of
:func:`~torchfilt.pipeline.offline.shard_plan` (recordings of equal length, at most
``batch_size`` per batch) and filters each batch as one Ray task on its worker's device (the GPU
where the task was given one, else the CPU). Each task writes its recordings' files straight into
the output folder, each file atomically (:mod:`torchfilt.io.atomic`), then one *completion marker*
per recording, ``.torchfilt/done/{name}.json``, holding the recording's summary entry (renamed
into place like every output, but not flushed to disk first: a marker lost or emptied by a system
crash only makes its recording be filtered again, while the estimates it vouches for were flushed
before it was written).

A recording is **complete** when its marker exists and so do the files the marker lists. The
marker is written last, after the recording's estimates (themselves written smoothed, plot, then
filtered), so a worker killed at any moment leaves each recording either complete or not: a file
of an incomplete recording is whole (atomic rename) and is rewritten, with the same bytes, by the
next attempt. A complete recording is never written again: a retried task and a re-run check the
markers first. The job's options and recordings are kept in ``.torchfilt/job.json``; running the
same job again into the same folder (the same recordings, in any order, and the same options)
does only the incomplete recordings, and a different job there is an error unless ``force``.
When every recording is complete, ``filter_summary.json`` is written as the local path writes it.

Because a batch's estimates can differ in their last bits with the batch's shape (batched
linear algebra), both the local path (:func:`~torchfilt.pipeline.offline.filter_recordings` with
the same ``batch_size``) and this one follow the same plan over the whole job, and a re-run
filters a batch with incomplete members whole (writing only those members): the files are
byte-identical to a local run's on the same kind of device.

The output folder and the recordings must be visible under the same paths on every worker (one
machine, or a shared filesystem).

**Training.** :func:`train_recipes_ray` trains several recipes, or one recipe over several
datasets, as parallel Ray tasks, each :func:`~torchfilt.pipeline.train_recipe` with its own run
directory (and so its own checkpoints and ``--resume``).

**Data-parallel fits.** :func:`calibrate_ray` and :func:`fit_measurement_only_ray` (likelihood or
EM) deal the recordings to Ray actors in one ``torch.distributed`` ``gloo`` group that sums what
the fit needs at every step, so the result is that of one process on all recordings. A lost
actor (killed, or past ``timeout`` at a collective) stops the group with a
:class:`~torchfilt.exceptions.WorkerError` naming its rank; ``resume=True`` continues from the
actors' checkpoints. With ``callback_on="driver"`` the per-iteration callback runs in the calling
process (rank 0's state, rank 0 waiting for it), so it need not pickle and may write local files.

**One recipe, data-parallel.** :func:`train_recipe_data_parallel` (``torchfilt train RECIPE
--ray --data-parallel N``) is :func:`~torchfilt.pipeline.train_recipe` whose calibration stage and
``states = "none"`` transition stage are these data-parallel fits on ``N`` actors (the other
stages run in this process): the same run directory, dataset log and bundle as a local run (the
calibrated and learned parameters equal up to the order of the sums), each stage's checkpoint a
folder of per-actor files, ``resume`` as for a local run.

**Modules.** :mod:`~torchfilt.pipeline.distributed.session` (importing Ray, opening a session),
:mod:`~torchfilt.pipeline.distributed.jobs` (a filter job's file and completion markers),
:mod:`~torchfilt.pipeline.distributed.filtering` (:func:`filter_recordings_ray`),
:mod:`~torchfilt.pipeline.distributed.recipes` (:func:`train_recipes_ray`),
:mod:`~torchfilt.pipeline.distributed.group` (the actors of a data-parallel fit and their errors),
:mod:`~torchfilt.pipeline.distributed.fits` (:func:`calibrate_ray`,
:func:`fit_measurement_only_ray`) and :mod:`~torchfilt.pipeline.distributed.data_parallel`
(:func:`train_recipe_data_parallel`). Every public name is importable from this package.
"""

from torchfilt.pipeline.distributed.data_parallel import (
    data_parallel_fitters as data_parallel_fitters,
)
from torchfilt.pipeline.distributed.data_parallel import train_recipe_data_parallel
from torchfilt.pipeline.distributed.filtering import filter_recordings_ray
from torchfilt.pipeline.distributed.fits import calibrate_ray, fit_measurement_only_ray
from torchfilt.pipeline.distributed.group import GROUP_TIMEOUT as GROUP_TIMEOUT
from torchfilt.pipeline.distributed.jobs import DONE_DIR, JOB_FILE
from torchfilt.pipeline.distributed.recipes import train_recipes_ray
from torchfilt.pipeline.distributed.session import INSTALL_HINT, import_ray, ray_session

__all__ = [
    "DONE_DIR",
    "INSTALL_HINT",
    "JOB_FILE",
    "calibrate_ray",
    "filter_recordings_ray",
    "fit_measurement_only_ray",
    "import_ray",
    "ray_session",
    "train_recipe_data_parallel",
    "train_recipes_ray",
]
