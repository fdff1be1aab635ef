"""The composition root: what a process holds once (settings, the body model, the Redis
connection with the repositories, stores and queue) and the use cases built on them, each
handed exactly the collaborators it uses, in dependency order. No service imports this module
or receives a :class:`Context`; the API builds one in its lifespan and hands each route its
service (``service.api.deps``), a worker builds one per process (:func:`worker_context`)."""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

from service.model.body.model import BodyModel, load_body_model
from service.settings import Settings, get_settings
from service.storage import redis as R
from service.storage.bases import BasisStore
from service.storage.drapes import DrapeStore
from service.storage.meshes import MeshStore
from service.storage.limits import JobTracker, RateLimiter
from service.storage.poses import PoseStore
from service.storage.queue import JobQueue, current_connection
from service.storage.records import CustomerRepo, GarmentRepo

from . import parallel
from .bodies import BodyCache
from .customers import CustomerService
from .drapes import ExactDrapes
from .editing import EditingService
from .editors import Editors
from .examples import Examples
from .garments import GarmentService
from .jobs import JobService
from .limits import Limits
from .poses import Poses
from .tryon import TryOnService


@dataclass(eq=False)
class Context:
    settings: Settings
    model: BodyModel
    conn: R.Connection
    customers_repo: CustomerRepo = field(init=False)
    garments_repo: GarmentRepo = field(init=False)
    bases: BasisStore = field(init=False)
    meshes: MeshStore = field(init=False)
    drape_store: DrapeStore = field(init=False)
    queue: JobQueue = field(init=False)
    bodies: BodyCache = field(init=False)
    editors: Editors = field(init=False)
    poses: Poses = field(init=False)
    customers: CustomerService = field(init=False)
    garments: GarmentService = field(init=False)
    tryon: TryOnService = field(init=False)
    drapes: ExactDrapes = field(init=False)
    jobs: JobService = field(init=False)
    editing: EditingService = field(init=False)
    rate_limiter: RateLimiter = field(init=False)
    limits: Limits = field(init=False)

    def __post_init__(self) -> None:
        settings, model, prefix = self.settings, self.model, self.settings.redis_prefix
        parallel.WORKERS = settings.pose_workers
        # storage
        self.customers_repo = CustomerRepo(self.conn, prefix)
        self.garments_repo = GarmentRepo(self.conn, prefix)
        self.bases = BasisStore(settings.data_dir)
        self.meshes = MeshStore(settings.data_dir)
        self.drape_store = DrapeStore(settings.data_dir)
        self.queue = JobQueue(self.conn)
        self.rate_limiter = RateLimiter(self.conn, prefix)
        self.limits = Limits(settings, self.rate_limiter, JobTracker(self.conn, prefix, self.queue))
        # per-process caches over the model and storage
        self.bodies = BodyCache(model)
        self.editors = Editors(model, self.meshes)
        self.poses = Poses(model, PoseStore(self.conn, prefix), self.bodies)
        # use cases, each after the ones it calls
        self.customers = CustomerService(model, self.customers_repo, self.queue, self.meshes, self.bodies,
                                         self.editors, self.poses, self.limits, settings.fit_timeout,
                                         self.drape_store)
        self.garments = GarmentService(settings, model, self.garments_repo, self.bases, self.queue, self.limits,
                                       lambda: self.examples, self.drape_store)
        self.tryon = TryOnService(model, self.customers_repo, self.garments_repo, self.customers, self.garments,
                                  self.poses)
        self.drapes = ExactDrapes(settings, model, self.customers_repo, self.garments_repo, self.customers,
                                  self.garments, self.tryon, self.queue, self.limits, self.drape_store)
        self.jobs = JobService(self.queue, self.customers_repo, self.customers)
        self.editing = EditingService(model, self.customers, self.editors)

    @functools.cached_property
    def examples(self) -> Examples:
        return _examples(self.model)

    @classmethod
    def open(cls, settings: Settings, model: BodyModel | None = None, conn: R.Connection | None = None) -> "Context":
        """A context on ``settings``' Redis (``conn`` when given) and body model."""
        model = model or load_body_model(settings.body_model_path)
        return cls(settings, model, conn if conn is not None else R.connect(settings))

    def close(self) -> None:
        R.close(self.conn)


@functools.lru_cache(maxsize=4)
def _examples(model: BodyModel) -> Examples:
    return Examples(model)


_worker_contexts: dict[int, Context] = {}


def worker_context() -> Context:
    """Inside a queued job: a context on the job's own connection (the settings and body model
    of the worker process, loaded once)."""
    settings = get_settings()
    conn = current_connection()
    if conn is None:
        conn = R.connect(settings)
    ctx = _worker_contexts.get(id(conn))
    if ctx is None:
        _worker_contexts.clear()
        ctx = _worker_contexts[id(conn)] = Context.open(settings, conn=conn)
    return ctx
