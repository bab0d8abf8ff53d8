from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class SharePhase(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SHARE_PHASE_UNSPECIFIED: _ClassVar[SharePhase]
    SHARE_PHASE_PILOT: _ClassVar[SharePhase]
    SHARE_PHASE_DIRECT: _ClassVar[SharePhase]
    SHARE_PHASE_REPLICA: _ClassVar[SharePhase]
    SHARE_PHASE_GATHER: _ClassVar[SharePhase]
    SHARE_PHASE_STOP: _ClassVar[SharePhase]
SHARE_PHASE_UNSPECIFIED: SharePhase
SHARE_PHASE_PILOT: SharePhase
SHARE_PHASE_DIRECT: SharePhase
SHARE_PHASE_REPLICA: SharePhase
SHARE_PHASE_GATHER: SharePhase
SHARE_PHASE_STOP: SharePhase

class ArrayChunk(_message.Message):
    __slots__ = ("name", "dtype", "shape", "offset", "total_bytes", "data")
    NAME_FIELD_NUMBER: _ClassVar[int]
    DTYPE_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    TOTAL_BYTES_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    name: str
    dtype: str
    shape: _containers.RepeatedScalarFieldContainer[int]
    offset: int
    total_bytes: int
    data: bytes
    def __init__(self, name: _Optional[str] = ..., dtype: _Optional[str] = ..., shape: _Optional[_Iterable[int]] = ..., offset: _Optional[int] = ..., total_bytes: _Optional[int] = ..., data: _Optional[bytes] = ...) -> None: ...

class FileChunk(_message.Message):
    __slots__ = ("path", "offset", "total_bytes", "data")
    PATH_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    TOTAL_BYTES_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    path: str
    offset: int
    total_bytes: int
    data: bytes
    def __init__(self, path: _Optional[str] = ..., offset: _Optional[int] = ..., total_bytes: _Optional[int] = ..., data: _Optional[bytes] = ...) -> None: ...

class Ledger(_message.Message):
    __slots__ = ("emitted", "absorbed", "escaped", "back_faces", "unshot", "in_flight", "imported", "exported", "closure", "residual", "unshot_abs", "in_flight_abs")
    EMITTED_FIELD_NUMBER: _ClassVar[int]
    ABSORBED_FIELD_NUMBER: _ClassVar[int]
    ESCAPED_FIELD_NUMBER: _ClassVar[int]
    BACK_FACES_FIELD_NUMBER: _ClassVar[int]
    UNSHOT_FIELD_NUMBER: _ClassVar[int]
    IN_FLIGHT_FIELD_NUMBER: _ClassVar[int]
    IMPORTED_FIELD_NUMBER: _ClassVar[int]
    EXPORTED_FIELD_NUMBER: _ClassVar[int]
    CLOSURE_FIELD_NUMBER: _ClassVar[int]
    RESIDUAL_FIELD_NUMBER: _ClassVar[int]
    UNSHOT_ABS_FIELD_NUMBER: _ClassVar[int]
    IN_FLIGHT_ABS_FIELD_NUMBER: _ClassVar[int]
    emitted: _containers.RepeatedScalarFieldContainer[float]
    absorbed: _containers.RepeatedScalarFieldContainer[float]
    escaped: _containers.RepeatedScalarFieldContainer[float]
    back_faces: _containers.RepeatedScalarFieldContainer[float]
    unshot: _containers.RepeatedScalarFieldContainer[float]
    in_flight: _containers.RepeatedScalarFieldContainer[float]
    imported: _containers.RepeatedScalarFieldContainer[float]
    exported: _containers.RepeatedScalarFieldContainer[float]
    closure: float
    residual: float
    unshot_abs: _containers.RepeatedScalarFieldContainer[float]
    in_flight_abs: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, emitted: _Optional[_Iterable[float]] = ..., absorbed: _Optional[_Iterable[float]] = ..., escaped: _Optional[_Iterable[float]] = ..., back_faces: _Optional[_Iterable[float]] = ..., unshot: _Optional[_Iterable[float]] = ..., in_flight: _Optional[_Iterable[float]] = ..., imported: _Optional[_Iterable[float]] = ..., exported: _Optional[_Iterable[float]] = ..., closure: _Optional[float] = ..., residual: _Optional[float] = ..., unshot_abs: _Optional[_Iterable[float]] = ..., in_flight_abs: _Optional[_Iterable[float]] = ...) -> None: ...

class SolverSettings(_message.Message):
    __slots__ = ("tol", "time_limit", "max_rays", "seed", "rays_per_power", "patch_size", "scale", "min_rays", "max_rays_per_shot", "batch_rays", "max_shooters", "snapshot_factor", "overshoot", "overshoot_min_return", "stiff_rays", "adaptive_bins", "snapshot_mb", "accuracy", "direct", "shadow_rays", "up", "two_sided", "workplane")
    TOL_FIELD_NUMBER: _ClassVar[int]
    TIME_LIMIT_FIELD_NUMBER: _ClassVar[int]
    MAX_RAYS_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    RAYS_PER_POWER_FIELD_NUMBER: _ClassVar[int]
    PATCH_SIZE_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    MIN_RAYS_FIELD_NUMBER: _ClassVar[int]
    MAX_RAYS_PER_SHOT_FIELD_NUMBER: _ClassVar[int]
    BATCH_RAYS_FIELD_NUMBER: _ClassVar[int]
    MAX_SHOOTERS_FIELD_NUMBER: _ClassVar[int]
    SNAPSHOT_FACTOR_FIELD_NUMBER: _ClassVar[int]
    OVERSHOOT_FIELD_NUMBER: _ClassVar[int]
    OVERSHOOT_MIN_RETURN_FIELD_NUMBER: _ClassVar[int]
    STIFF_RAYS_FIELD_NUMBER: _ClassVar[int]
    ADAPTIVE_BINS_FIELD_NUMBER: _ClassVar[int]
    SNAPSHOT_MB_FIELD_NUMBER: _ClassVar[int]
    ACCURACY_FIELD_NUMBER: _ClassVar[int]
    DIRECT_FIELD_NUMBER: _ClassVar[int]
    SHADOW_RAYS_FIELD_NUMBER: _ClassVar[int]
    UP_FIELD_NUMBER: _ClassVar[int]
    TWO_SIDED_FIELD_NUMBER: _ClassVar[int]
    WORKPLANE_FIELD_NUMBER: _ClassVar[int]
    tol: float
    time_limit: float
    max_rays: int
    seed: int
    rays_per_power: float
    patch_size: float
    scale: float
    min_rays: int
    max_rays_per_shot: int
    batch_rays: int
    max_shooters: int
    snapshot_factor: float
    overshoot: float
    overshoot_min_return: float
    stiff_rays: bool
    adaptive_bins: bool
    snapshot_mb: float
    accuracy: float
    direct: bool
    shadow_rays: int
    up: str
    two_sided: bool
    workplane: float
    def __init__(self, tol: _Optional[float] = ..., time_limit: _Optional[float] = ..., max_rays: _Optional[int] = ..., seed: _Optional[int] = ..., rays_per_power: _Optional[float] = ..., patch_size: _Optional[float] = ..., scale: _Optional[float] = ..., min_rays: _Optional[int] = ..., max_rays_per_shot: _Optional[int] = ..., batch_rays: _Optional[int] = ..., max_shooters: _Optional[int] = ..., snapshot_factor: _Optional[float] = ..., overshoot: _Optional[float] = ..., overshoot_min_return: _Optional[float] = ..., stiff_rays: _Optional[bool] = ..., adaptive_bins: _Optional[bool] = ..., snapshot_mb: _Optional[float] = ..., accuracy: _Optional[float] = ..., direct: _Optional[bool] = ..., shadow_rays: _Optional[int] = ..., up: _Optional[str] = ..., two_sided: _Optional[bool] = ..., workplane: _Optional[float] = ...) -> None: ...

class DivideSettings(_message.Message):
    __slots__ = ("subscenes", "iterations", "solid", "cell_size", "mode", "max_iterations")
    SUBSCENES_FIELD_NUMBER: _ClassVar[int]
    ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    SOLID_FIELD_NUMBER: _ClassVar[int]
    CELL_SIZE_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    MAX_ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    subscenes: int
    iterations: int
    solid: int
    cell_size: float
    mode: str
    max_iterations: int
    def __init__(self, subscenes: _Optional[int] = ..., iterations: _Optional[int] = ..., solid: _Optional[int] = ..., cell_size: _Optional[float] = ..., mode: _Optional[str] = ..., max_iterations: _Optional[int] = ...) -> None: ...

class JobSpec(_message.Message):
    __slots__ = ("scene", "solver", "divide", "preview_width", "preview_height", "luminaires", "daylight")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    SOLVER_FIELD_NUMBER: _ClassVar[int]
    DIVIDE_FIELD_NUMBER: _ClassVar[int]
    PREVIEW_WIDTH_FIELD_NUMBER: _ClassVar[int]
    PREVIEW_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    LUMINAIRES_FIELD_NUMBER: _ClassVar[int]
    DAYLIGHT_FIELD_NUMBER: _ClassVar[int]
    scene: str
    solver: SolverSettings
    divide: DivideSettings
    preview_width: int
    preview_height: int
    luminaires: str
    daylight: str
    def __init__(self, scene: _Optional[str] = ..., solver: _Optional[_Union[SolverSettings, _Mapping]] = ..., divide: _Optional[_Union[DivideSettings, _Mapping]] = ..., preview_width: _Optional[int] = ..., preview_height: _Optional[int] = ..., luminaires: _Optional[str] = ..., daylight: _Optional[str] = ...) -> None: ...

class SubmitRequest(_message.Message):
    __slots__ = ("spec", "file")
    SPEC_FIELD_NUMBER: _ClassVar[int]
    FILE_FIELD_NUMBER: _ClassVar[int]
    spec: JobSpec
    file: FileChunk
    def __init__(self, spec: _Optional[_Union[JobSpec, _Mapping]] = ..., file: _Optional[_Union[FileChunk, _Mapping]] = ...) -> None: ...

class JobRef(_message.Message):
    __slots__ = ("job_id",)
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    def __init__(self, job_id: _Optional[str] = ...) -> None: ...

class JobSummary(_message.Message):
    __slots__ = ("job_id", "state", "scene", "subscenes", "elapsed_s", "residual", "workers", "error")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    SUBSCENES_FIELD_NUMBER: _ClassVar[int]
    ELAPSED_S_FIELD_NUMBER: _ClassVar[int]
    RESIDUAL_FIELD_NUMBER: _ClassVar[int]
    WORKERS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    state: str
    scene: str
    subscenes: int
    elapsed_s: float
    residual: float
    workers: _containers.RepeatedScalarFieldContainer[str]
    error: str
    def __init__(self, job_id: _Optional[str] = ..., state: _Optional[str] = ..., scene: _Optional[str] = ..., subscenes: _Optional[int] = ..., elapsed_s: _Optional[float] = ..., residual: _Optional[float] = ..., workers: _Optional[_Iterable[str]] = ..., error: _Optional[str] = ...) -> None: ...

class ListJobsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class JobList(_message.Message):
    __slots__ = ("jobs",)
    JOBS_FIELD_NUMBER: _ClassVar[int]
    jobs: _containers.RepeatedCompositeFieldContainer[JobSummary]
    def __init__(self, jobs: _Optional[_Iterable[_Union[JobSummary, _Mapping]]] = ...) -> None: ...

class SubsceneProgress(_message.Message):
    __slots__ = ("cell", "worker", "shots", "rays", "residual", "twin_bytes", "reassigned")
    CELL_FIELD_NUMBER: _ClassVar[int]
    WORKER_FIELD_NUMBER: _ClassVar[int]
    SHOTS_FIELD_NUMBER: _ClassVar[int]
    RAYS_FIELD_NUMBER: _ClassVar[int]
    RESIDUAL_FIELD_NUMBER: _ClassVar[int]
    TWIN_BYTES_FIELD_NUMBER: _ClassVar[int]
    REASSIGNED_FIELD_NUMBER: _ClassVar[int]
    cell: int
    worker: str
    shots: int
    rays: int
    residual: float
    twin_bytes: int
    reassigned: int
    def __init__(self, cell: _Optional[int] = ..., worker: _Optional[str] = ..., shots: _Optional[int] = ..., rays: _Optional[int] = ..., residual: _Optional[float] = ..., twin_bytes: _Optional[int] = ..., reassigned: _Optional[int] = ...) -> None: ...

class Progress(_message.Message):
    __slots__ = ("job", "barrier", "shots", "rays", "rms_estimate", "ledger", "subscenes", "bytes_relayed", "error", "accuracy")
    JOB_FIELD_NUMBER: _ClassVar[int]
    BARRIER_FIELD_NUMBER: _ClassVar[int]
    SHOTS_FIELD_NUMBER: _ClassVar[int]
    RAYS_FIELD_NUMBER: _ClassVar[int]
    RMS_ESTIMATE_FIELD_NUMBER: _ClassVar[int]
    LEDGER_FIELD_NUMBER: _ClassVar[int]
    SUBSCENES_FIELD_NUMBER: _ClassVar[int]
    BYTES_RELAYED_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    ACCURACY_FIELD_NUMBER: _ClassVar[int]
    job: JobSummary
    barrier: int
    shots: int
    rays: int
    rms_estimate: float
    ledger: Ledger
    subscenes: _containers.RepeatedCompositeFieldContainer[SubsceneProgress]
    bytes_relayed: int
    error: ErrorEstimate
    accuracy: float
    def __init__(self, job: _Optional[_Union[JobSummary, _Mapping]] = ..., barrier: _Optional[int] = ..., shots: _Optional[int] = ..., rays: _Optional[int] = ..., rms_estimate: _Optional[float] = ..., ledger: _Optional[_Union[Ledger, _Mapping]] = ..., subscenes: _Optional[_Iterable[_Union[SubsceneProgress, _Mapping]]] = ..., bytes_relayed: _Optional[int] = ..., error: _Optional[_Union[ErrorEstimate, _Mapping]] = ..., accuracy: _Optional[float] = ...) -> None: ...

class ErrorEstimate(_message.Message):
    __slots__ = ("rms", "rms_norm", "rms_refl", "noise_refl", "bias_refl", "method")
    RMS_FIELD_NUMBER: _ClassVar[int]
    RMS_NORM_FIELD_NUMBER: _ClassVar[int]
    RMS_REFL_FIELD_NUMBER: _ClassVar[int]
    NOISE_REFL_FIELD_NUMBER: _ClassVar[int]
    BIAS_REFL_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    rms: float
    rms_norm: float
    rms_refl: float
    noise_refl: float
    bias_refl: float
    method: str
    def __init__(self, rms: _Optional[float] = ..., rms_norm: _Optional[float] = ..., rms_refl: _Optional[float] = ..., noise_refl: _Optional[float] = ..., bias_refl: _Optional[float] = ..., method: _Optional[str] = ...) -> None: ...

class WorkerInfo(_message.Message):
    __slots__ = ("address", "capacity", "name", "alive", "load")
    ADDRESS_FIELD_NUMBER: _ClassVar[int]
    CAPACITY_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    ALIVE_FIELD_NUMBER: _ClassVar[int]
    LOAD_FIELD_NUMBER: _ClassVar[int]
    address: str
    capacity: int
    name: str
    alive: bool
    load: int
    def __init__(self, address: _Optional[str] = ..., capacity: _Optional[int] = ..., name: _Optional[str] = ..., alive: _Optional[bool] = ..., load: _Optional[int] = ...) -> None: ...

class ListWorkersRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class WorkerList(_message.Message):
    __slots__ = ("workers",)
    WORKERS_FIELD_NUMBER: _ClassVar[int]
    workers: _containers.RepeatedCompositeFieldContainer[WorkerInfo]
    def __init__(self, workers: _Optional[_Iterable[_Union[WorkerInfo, _Mapping]]] = ...) -> None: ...

class RegisterReply(_message.Message):
    __slots__ = ("worker_id",)
    WORKER_ID_FIELD_NUMBER: _ClassVar[int]
    worker_id: str
    def __init__(self, worker_id: _Optional[str] = ...) -> None: ...

class SubsceneKey(_message.Message):
    __slots__ = ("job_id", "cell")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    CELL_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    cell: int
    def __init__(self, job_id: _Optional[str] = ..., cell: _Optional[int] = ...) -> None: ...

class SubsceneHeader(_message.Message):
    __slots__ = ("key", "solver", "power_per_ray", "mode", "names", "local_target")
    KEY_FIELD_NUMBER: _ClassVar[int]
    SOLVER_FIELD_NUMBER: _ClassVar[int]
    POWER_PER_RAY_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    NAMES_FIELD_NUMBER: _ClassVar[int]
    LOCAL_TARGET_FIELD_NUMBER: _ClassVar[int]
    key: SubsceneKey
    solver: SolverSettings
    power_per_ray: float
    mode: str
    names: _containers.RepeatedScalarFieldContainer[str]
    local_target: float
    def __init__(self, key: _Optional[_Union[SubsceneKey, _Mapping]] = ..., solver: _Optional[_Union[SolverSettings, _Mapping]] = ..., power_per_ray: _Optional[float] = ..., mode: _Optional[str] = ..., names: _Optional[_Iterable[str]] = ..., local_target: _Optional[float] = ...) -> None: ...

class LoadRequest(_message.Message):
    __slots__ = ("header", "array")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    ARRAY_FIELD_NUMBER: _ClassVar[int]
    header: SubsceneHeader
    array: ArrayChunk
    def __init__(self, header: _Optional[_Union[SubsceneHeader, _Mapping]] = ..., array: _Optional[_Union[ArrayChunk, _Mapping]] = ...) -> None: ...

class SubsceneStatus(_message.Message):
    __slots__ = ("key", "ledger", "shots", "rays", "twin_entries", "twin_bytes", "compute_s", "area", "return_tallies", "twins_delivered", "twin_blocks", "batches", "trace_s", "back_by_obj", "noise")
    KEY_FIELD_NUMBER: _ClassVar[int]
    LEDGER_FIELD_NUMBER: _ClassVar[int]
    SHOTS_FIELD_NUMBER: _ClassVar[int]
    RAYS_FIELD_NUMBER: _ClassVar[int]
    TWIN_ENTRIES_FIELD_NUMBER: _ClassVar[int]
    TWIN_BYTES_FIELD_NUMBER: _ClassVar[int]
    COMPUTE_S_FIELD_NUMBER: _ClassVar[int]
    AREA_FIELD_NUMBER: _ClassVar[int]
    RETURN_TALLIES_FIELD_NUMBER: _ClassVar[int]
    TWINS_DELIVERED_FIELD_NUMBER: _ClassVar[int]
    TWIN_BLOCKS_FIELD_NUMBER: _ClassVar[int]
    BATCHES_FIELD_NUMBER: _ClassVar[int]
    TRACE_S_FIELD_NUMBER: _ClassVar[int]
    BACK_BY_OBJ_FIELD_NUMBER: _ClassVar[int]
    NOISE_FIELD_NUMBER: _ClassVar[int]
    key: SubsceneKey
    ledger: Ledger
    shots: int
    rays: int
    twin_entries: int
    twin_bytes: int
    compute_s: float
    area: float
    return_tallies: _containers.RepeatedScalarFieldContainer[float]
    twins_delivered: int
    twin_blocks: int
    batches: int
    trace_s: float
    back_by_obj: _containers.RepeatedScalarFieldContainer[float]
    noise: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, key: _Optional[_Union[SubsceneKey, _Mapping]] = ..., ledger: _Optional[_Union[Ledger, _Mapping]] = ..., shots: _Optional[int] = ..., rays: _Optional[int] = ..., twin_entries: _Optional[int] = ..., twin_bytes: _Optional[int] = ..., compute_s: _Optional[float] = ..., area: _Optional[float] = ..., return_tallies: _Optional[_Iterable[float]] = ..., twins_delivered: _Optional[int] = ..., twin_blocks: _Optional[int] = ..., batches: _Optional[int] = ..., trace_s: _Optional[float] = ..., back_by_obj: _Optional[_Iterable[float]] = ..., noise: _Optional[_Iterable[float]] = ...) -> None: ...

class IterateRequest(_message.Message):
    __slots__ = ("key", "batches", "ambient_scale", "ambient_rest", "ray_factor", "return_ratio", "time_left_s", "goal_share", "rays_left")
    KEY_FIELD_NUMBER: _ClassVar[int]
    BATCHES_FIELD_NUMBER: _ClassVar[int]
    AMBIENT_SCALE_FIELD_NUMBER: _ClassVar[int]
    AMBIENT_REST_FIELD_NUMBER: _ClassVar[int]
    RAY_FACTOR_FIELD_NUMBER: _ClassVar[int]
    RETURN_RATIO_FIELD_NUMBER: _ClassVar[int]
    TIME_LEFT_S_FIELD_NUMBER: _ClassVar[int]
    GOAL_SHARE_FIELD_NUMBER: _ClassVar[int]
    RAYS_LEFT_FIELD_NUMBER: _ClassVar[int]
    key: SubsceneKey
    batches: int
    ambient_scale: _containers.RepeatedScalarFieldContainer[float]
    ambient_rest: _containers.RepeatedScalarFieldContainer[float]
    ray_factor: float
    return_ratio: float
    time_left_s: float
    goal_share: float
    rays_left: int
    def __init__(self, key: _Optional[_Union[SubsceneKey, _Mapping]] = ..., batches: _Optional[int] = ..., ambient_scale: _Optional[_Iterable[float]] = ..., ambient_rest: _Optional[_Iterable[float]] = ..., ray_factor: _Optional[float] = ..., return_ratio: _Optional[float] = ..., time_left_s: _Optional[float] = ..., goal_share: _Optional[float] = ..., rays_left: _Optional[int] = ...) -> None: ...

class IterateReply(_message.Message):
    __slots__ = ("array", "status")
    ARRAY_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    array: ArrayChunk
    status: SubsceneStatus
    def __init__(self, array: _Optional[_Union[ArrayChunk, _Mapping]] = ..., status: _Optional[_Union[SubsceneStatus, _Mapping]] = ...) -> None: ...

class DeliverRequest(_message.Message):
    __slots__ = ("key", "array")
    KEY_FIELD_NUMBER: _ClassVar[int]
    ARRAY_FIELD_NUMBER: _ClassVar[int]
    key: SubsceneKey
    array: ArrayChunk
    def __init__(self, key: _Optional[_Union[SubsceneKey, _Mapping]] = ..., array: _Optional[_Union[ArrayChunk, _Mapping]] = ...) -> None: ...

class Empty(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ShareHeader(_message.Message):
    __slots__ = ("job_id", "phase", "index", "count", "solver", "names", "scene")
    JOB_ID_FIELD_NUMBER: _ClassVar[int]
    PHASE_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    SOLVER_FIELD_NUMBER: _ClassVar[int]
    NAMES_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    job_id: str
    phase: SharePhase
    index: int
    count: int
    solver: SolverSettings
    names: _containers.RepeatedScalarFieldContainer[str]
    scene: bool
    def __init__(self, job_id: _Optional[str] = ..., phase: _Optional[_Union[SharePhase, str]] = ..., index: _Optional[int] = ..., count: _Optional[int] = ..., solver: _Optional[_Union[SolverSettings, _Mapping]] = ..., names: _Optional[_Iterable[str]] = ..., scene: _Optional[bool] = ...) -> None: ...

class ShareRequest(_message.Message):
    __slots__ = ("header", "array", "scene", "tally", "shot")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    ARRAY_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    TALLY_FIELD_NUMBER: _ClassVar[int]
    SHOT_FIELD_NUMBER: _ClassVar[int]
    header: ShareHeader
    array: ArrayChunk
    scene: ArrayChunk
    tally: ArrayChunk
    shot: ArrayChunk
    def __init__(self, header: _Optional[_Union[ShareHeader, _Mapping]] = ..., array: _Optional[_Union[ArrayChunk, _Mapping]] = ..., scene: _Optional[_Union[ArrayChunk, _Mapping]] = ..., tally: _Optional[_Union[ArrayChunk, _Mapping]] = ..., shot: _Optional[_Union[ArrayChunk, _Mapping]] = ...) -> None: ...
