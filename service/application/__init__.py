"""The application layer: use cases over typed records (:mod:`service.records`), called by the
HTTP routes (``service.api``) and by the queued jobs (``worker.jobs``) alike.

* :mod:`.context` -- the composition root: everything a process holds once (settings, body
  model, repositories, queue, caches) and the use cases built on them, each given exactly its
  collaborators (:class:`~.context.Context`; no use case imports it);
* :mod:`.customers`, :mod:`.garments`, :mod:`.tryon`, :mod:`.jobs`, :mod:`.avatars` -- the use
  cases;
* :mod:`.uploads` -- the upload gateway: every uploaded file is read and checked here;
* :mod:`.scenes` -- GLB assembly (avatar, garments, bases) from model arrays;
* :mod:`.errors` -- what a use case refuses, with why (the routes map them to HTTP statuses).

No FastAPI imports here.
"""
