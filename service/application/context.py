"""What a process holds once: settings, the body model, the Redis connection with the
repositories and the queue, the basis files, and the use cases built on them. The API builds one
in its lifespan, a worker one per process (:func:`worker_context`)."""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import redis

from service.model.body.model import BodyModel, load_body_model
from service.settings import Settings, get_settings
from service.storage import redis as R
from service.storage.bases import BasisStore
from service.storage.meshes import MeshStore
from service.storage.limits import RateLimiter
from service.storage.queue import JobQueue, current_connection
from service.storage.records import CustomerRepo, GarmentRepo

from . import parallel
from .customers import CustomerService
from .editing import EditingService
from .examples import Examples
from .garments import GarmentService
from .jobs import JobService
from .limits import Limits
from .tryon import TryOnService


@dataclass(eq=False)
class Context:
    settings: Settings
    model: BodyModel
    conn: redis.Redis
    customers_repo: CustomerRepo = field(init=False)
    garments_repo: GarmentRepo = field(init=False)
    bases: BasisStore = field(init=False)
    meshes: MeshStore = field(init=False)
    queue: JobQueue = field(init=False)
    customers: CustomerService = field(init=False)
    garments: GarmentService = field(init=False)
    tryon: TryOnService = field(init=False)
    jobs: JobService = field(init=False)
    editing: EditingService = field(init=False)
    rate_limiter: RateLimiter = field(init=False)
    limits: Limits = field(init=False)

    def __post_init__(self) -> None:
        prefix = self.settings.redis_prefix
        parallel.WORKERS = self.settings.pose_workers
        self.customers_repo = CustomerRepo(self.conn, prefix)
        self.garments_repo = GarmentRepo(self.conn, prefix)
        self.bases = BasisStore(self.settings.data_dir)
        self.meshes = MeshStore(self.settings.data_dir)
        self.queue = JobQueue(self.conn)
        self.customers = CustomerService(self)
        self.garments = GarmentService(self)
        self.tryon = TryOnService(self)
        self.jobs = JobService(self)
        self.editing = EditingService(self)
        self.rate_limiter = RateLimiter(self.conn, prefix)
        self.limits = Limits(self)

    @functools.cached_property
    def examples(self) -> Examples:
        return _examples(self.model)

    @classmethod
    def open(cls, settings: Settings, model: BodyModel | None = None, conn: redis.Redis | None = None) -> "Context":
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
