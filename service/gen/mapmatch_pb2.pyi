from google.protobuf import struct_pb2 as _struct_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class State(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STATE_UNSPECIFIED: _ClassVar[State]
    STATE_INITIALISING: _ClassVar[State]
    STATE_ON_ROAD: _ClassVar[State]
    STATE_AMBIGUOUS: _ClassVar[State]
    STATE_OFF_ROAD: _ClassVar[State]
    STATE_REINITIALISED: _ClassVar[State]

class Turn(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    TURN_UNSPECIFIED: _ClassVar[Turn]
    TURN_NONE: _ClassVar[Turn]
    TURN_LEFT: _ClassVar[Turn]
    TURN_RIGHT: _ClassVar[Turn]
    TURN_STRAIGHT: _ClassVar[Turn]
    TURN_U_TURN: _ClassVar[Turn]

class PointStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    POINT_STATUS_UNSPECIFIED: _ClassVar[PointStatus]
    POINT_STATUS_MATCHED: _ClassVar[PointStatus]
    POINT_STATUS_INTERPOLATED: _ClassVar[PointStatus]
    POINT_STATUS_UNMATCHED: _ClassVar[PointStatus]
STATE_UNSPECIFIED: State
STATE_INITIALISING: State
STATE_ON_ROAD: State
STATE_AMBIGUOUS: State
STATE_OFF_ROAD: State
STATE_REINITIALISED: State
TURN_UNSPECIFIED: Turn
TURN_NONE: Turn
TURN_LEFT: Turn
TURN_RIGHT: Turn
TURN_STRAIGHT: Turn
TURN_U_TURN: Turn
POINT_STATUS_UNSPECIFIED: PointStatus
POINT_STATUS_MATCHED: PointStatus
POINT_STATUS_INTERPOLATED: PointStatus
POINT_STATUS_UNMATCHED: PointStatus

class PositionCovariance(_message.Message):
    __slots__ = ("var_e", "cov_en", "var_n")
    VAR_E_FIELD_NUMBER: _ClassVar[int]
    COV_EN_FIELD_NUMBER: _ClassVar[int]
    VAR_N_FIELD_NUMBER: _ClassVar[int]
    var_e: float
    cov_en: float
    var_n: float
    def __init__(self, var_e: _Optional[float] = ..., cov_en: _Optional[float] = ..., var_n: _Optional[float] = ...) -> None: ...

class Fix(_message.Message):
    __slots__ = ("time", "lat", "lon", "heading", "pos_sigma", "heading_sigma", "speed", "distance", "gps_valid", "pos_cov")
    TIME_FIELD_NUMBER: _ClassVar[int]
    LAT_FIELD_NUMBER: _ClassVar[int]
    LON_FIELD_NUMBER: _ClassVar[int]
    HEADING_FIELD_NUMBER: _ClassVar[int]
    POS_SIGMA_FIELD_NUMBER: _ClassVar[int]
    HEADING_SIGMA_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    GPS_VALID_FIELD_NUMBER: _ClassVar[int]
    POS_COV_FIELD_NUMBER: _ClassVar[int]
    time: float
    lat: float
    lon: float
    heading: float
    pos_sigma: float
    heading_sigma: float
    speed: float
    distance: float
    gps_valid: bool
    pos_cov: PositionCovariance
    def __init__(self, time: _Optional[float] = ..., lat: _Optional[float] = ..., lon: _Optional[float] = ..., heading: _Optional[float] = ..., pos_sigma: _Optional[float] = ..., heading_sigma: _Optional[float] = ..., speed: _Optional[float] = ..., distance: _Optional[float] = ..., gps_valid: _Optional[bool] = ..., pos_cov: _Optional[_Union[PositionCovariance, _Mapping]] = ...) -> None: ...

class FixRequest(_message.Message):
    __slots__ = ("map_id", "vehicle_id", "seq", "fix")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    FIX_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    vehicle_id: str
    seq: int
    fix: Fix
    def __init__(self, map_id: _Optional[str] = ..., vehicle_id: _Optional[str] = ..., seq: _Optional[int] = ..., fix: _Optional[_Union[Fix, _Mapping]] = ...) -> None: ...

class FixBatch(_message.Message):
    __slots__ = ("fixes",)
    FIXES_FIELD_NUMBER: _ClassVar[int]
    fixes: _containers.RepeatedCompositeFieldContainer[FixRequest]
    def __init__(self, fixes: _Optional[_Iterable[_Union[FixRequest, _Mapping]]] = ...) -> None: ...

class SnapBatch(_message.Message):
    __slots__ = ("responses", "error")
    RESPONSES_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    responses: _containers.RepeatedCompositeFieldContainer[SnapResponse]
    error: Error
    def __init__(self, responses: _Optional[_Iterable[_Union[SnapResponse, _Mapping]]] = ..., error: _Optional[_Union[Error, _Mapping]] = ...) -> None: ...

class Candidate(_message.Message):
    __slots__ = ("edge", "u", "v", "way_id", "probability", "offset", "dist")
    EDGE_FIELD_NUMBER: _ClassVar[int]
    U_FIELD_NUMBER: _ClassVar[int]
    V_FIELD_NUMBER: _ClassVar[int]
    WAY_ID_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    DIST_FIELD_NUMBER: _ClassVar[int]
    edge: int
    u: int
    v: int
    way_id: int
    probability: float
    offset: float
    dist: float
    def __init__(self, edge: _Optional[int] = ..., u: _Optional[int] = ..., v: _Optional[int] = ..., way_id: _Optional[int] = ..., probability: _Optional[float] = ..., offset: _Optional[float] = ..., dist: _Optional[float] = ...) -> None: ...

class Correction(_message.Message):
    __slots__ = ("time_from", "time_to", "edges", "replaced_edges", "edge_times")
    TIME_FROM_FIELD_NUMBER: _ClassVar[int]
    TIME_TO_FIELD_NUMBER: _ClassVar[int]
    EDGES_FIELD_NUMBER: _ClassVar[int]
    REPLACED_EDGES_FIELD_NUMBER: _ClassVar[int]
    EDGE_TIMES_FIELD_NUMBER: _ClassVar[int]
    time_from: float
    time_to: float
    edges: _containers.RepeatedScalarFieldContainer[int]
    replaced_edges: _containers.RepeatedScalarFieldContainer[int]
    edge_times: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, time_from: _Optional[float] = ..., time_to: _Optional[float] = ..., edges: _Optional[_Iterable[int]] = ..., replaced_edges: _Optional[_Iterable[int]] = ..., edge_times: _Optional[_Iterable[float]] = ...) -> None: ...

class SnapResult(_message.Message):
    __slots__ = ("time", "state", "edge", "u", "v", "way_id", "offset", "lat", "lon", "bearing", "dist", "turn", "candidates", "correction", "raw_lat", "raw_lon", "name", "road_class", "speed_kph", "map_aided")
    TIME_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    EDGE_FIELD_NUMBER: _ClassVar[int]
    U_FIELD_NUMBER: _ClassVar[int]
    V_FIELD_NUMBER: _ClassVar[int]
    WAY_ID_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    LAT_FIELD_NUMBER: _ClassVar[int]
    LON_FIELD_NUMBER: _ClassVar[int]
    BEARING_FIELD_NUMBER: _ClassVar[int]
    DIST_FIELD_NUMBER: _ClassVar[int]
    TURN_FIELD_NUMBER: _ClassVar[int]
    CANDIDATES_FIELD_NUMBER: _ClassVar[int]
    CORRECTION_FIELD_NUMBER: _ClassVar[int]
    RAW_LAT_FIELD_NUMBER: _ClassVar[int]
    RAW_LON_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    ROAD_CLASS_FIELD_NUMBER: _ClassVar[int]
    SPEED_KPH_FIELD_NUMBER: _ClassVar[int]
    MAP_AIDED_FIELD_NUMBER: _ClassVar[int]
    time: float
    state: State
    edge: int
    u: int
    v: int
    way_id: int
    offset: float
    lat: float
    lon: float
    bearing: float
    dist: float
    turn: Turn
    candidates: _containers.RepeatedCompositeFieldContainer[Candidate]
    correction: Correction
    raw_lat: float
    raw_lon: float
    name: str
    road_class: str
    speed_kph: float
    map_aided: MapAidedMeasurement
    def __init__(self, time: _Optional[float] = ..., state: _Optional[_Union[State, str]] = ..., edge: _Optional[int] = ..., u: _Optional[int] = ..., v: _Optional[int] = ..., way_id: _Optional[int] = ..., offset: _Optional[float] = ..., lat: _Optional[float] = ..., lon: _Optional[float] = ..., bearing: _Optional[float] = ..., dist: _Optional[float] = ..., turn: _Optional[_Union[Turn, str]] = ..., candidates: _Optional[_Iterable[_Union[Candidate, _Mapping]]] = ..., correction: _Optional[_Union[Correction, _Mapping]] = ..., raw_lat: _Optional[float] = ..., raw_lon: _Optional[float] = ..., name: _Optional[str] = ..., road_class: _Optional[str] = ..., speed_kph: _Optional[float] = ..., map_aided: _Optional[_Union[MapAidedMeasurement, _Mapping]] = ...) -> None: ...

class MapAidedMeasurement(_message.Message):
    __slots__ = ("lat", "lon", "cov", "along_sigma", "cross_sigma", "heading", "heading_sigma", "probability", "usable", "reason")
    LAT_FIELD_NUMBER: _ClassVar[int]
    LON_FIELD_NUMBER: _ClassVar[int]
    COV_FIELD_NUMBER: _ClassVar[int]
    ALONG_SIGMA_FIELD_NUMBER: _ClassVar[int]
    CROSS_SIGMA_FIELD_NUMBER: _ClassVar[int]
    HEADING_FIELD_NUMBER: _ClassVar[int]
    HEADING_SIGMA_FIELD_NUMBER: _ClassVar[int]
    PROBABILITY_FIELD_NUMBER: _ClassVar[int]
    USABLE_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    lat: float
    lon: float
    cov: _containers.RepeatedScalarFieldContainer[float]
    along_sigma: float
    cross_sigma: float
    heading: float
    heading_sigma: float
    probability: float
    usable: bool
    reason: str
    def __init__(self, lat: _Optional[float] = ..., lon: _Optional[float] = ..., cov: _Optional[_Iterable[float]] = ..., along_sigma: _Optional[float] = ..., cross_sigma: _Optional[float] = ..., heading: _Optional[float] = ..., heading_sigma: _Optional[float] = ..., probability: _Optional[float] = ..., usable: _Optional[bool] = ..., reason: _Optional[str] = ...) -> None: ...

class Error(_message.Message):
    __slots__ = ("code", "field", "message")
    CODE_FIELD_NUMBER: _ClassVar[int]
    FIELD_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: int
    field: str
    message: str
    def __init__(self, code: _Optional[int] = ..., field: _Optional[str] = ..., message: _Optional[str] = ...) -> None: ...

class SnapResponse(_message.Message):
    __slots__ = ("map_id", "vehicle_id", "seq", "result", "error")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    vehicle_id: str
    seq: int
    result: SnapResult
    error: Error
    def __init__(self, map_id: _Optional[str] = ..., vehicle_id: _Optional[str] = ..., seq: _Optional[int] = ..., result: _Optional[_Union[SnapResult, _Mapping]] = ..., error: _Optional[_Union[Error, _Mapping]] = ...) -> None: ...

class Track(_message.Message):
    __slots__ = ("track_id", "time", "lat", "lon", "heading", "speed", "pos_sigma", "distance")
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    LAT_FIELD_NUMBER: _ClassVar[int]
    LON_FIELD_NUMBER: _ClassVar[int]
    HEADING_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    POS_SIGMA_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    track_id: str
    time: _containers.RepeatedScalarFieldContainer[float]
    lat: _containers.RepeatedScalarFieldContainer[float]
    lon: _containers.RepeatedScalarFieldContainer[float]
    heading: _containers.RepeatedScalarFieldContainer[float]
    speed: _containers.RepeatedScalarFieldContainer[float]
    pos_sigma: _containers.RepeatedScalarFieldContainer[float]
    distance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, track_id: _Optional[str] = ..., time: _Optional[_Iterable[float]] = ..., lat: _Optional[_Iterable[float]] = ..., lon: _Optional[_Iterable[float]] = ..., heading: _Optional[_Iterable[float]] = ..., speed: _Optional[_Iterable[float]] = ..., pos_sigma: _Optional[_Iterable[float]] = ..., distance: _Optional[_Iterable[float]] = ...) -> None: ...

class MatchTrackRequest(_message.Message):
    __slots__ = ("map_id", "track")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    TRACK_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    track: Track
    def __init__(self, map_id: _Optional[str] = ..., track: _Optional[_Union[Track, _Mapping]] = ...) -> None: ...

class MatchTracksRequest(_message.Message):
    __slots__ = ("map_id", "tracks")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    TRACKS_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    tracks: _containers.RepeatedCompositeFieldContainer[Track]
    def __init__(self, map_id: _Optional[str] = ..., tracks: _Optional[_Iterable[_Union[Track, _Mapping]]] = ...) -> None: ...

class MatchedPoint(_message.Message):
    __slots__ = ("index", "status", "edge", "offset", "lat", "lon", "dist")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    EDGE_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    LAT_FIELD_NUMBER: _ClassVar[int]
    LON_FIELD_NUMBER: _ClassVar[int]
    DIST_FIELD_NUMBER: _ClassVar[int]
    index: int
    status: PointStatus
    edge: int
    offset: float
    lat: float
    lon: float
    dist: float
    def __init__(self, index: _Optional[int] = ..., status: _Optional[_Union[PointStatus, str]] = ..., edge: _Optional[int] = ..., offset: _Optional[float] = ..., lat: _Optional[float] = ..., lon: _Optional[float] = ..., dist: _Optional[float] = ...) -> None: ...

class Route(_message.Message):
    __slots__ = ("edges", "way_ids", "lat", "lon")
    EDGES_FIELD_NUMBER: _ClassVar[int]
    WAY_IDS_FIELD_NUMBER: _ClassVar[int]
    LAT_FIELD_NUMBER: _ClassVar[int]
    LON_FIELD_NUMBER: _ClassVar[int]
    edges: _containers.RepeatedScalarFieldContainer[int]
    way_ids: _containers.RepeatedScalarFieldContainer[int]
    lat: _containers.RepeatedScalarFieldContainer[float]
    lon: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, edges: _Optional[_Iterable[int]] = ..., way_ids: _Optional[_Iterable[int]] = ..., lat: _Optional[_Iterable[float]] = ..., lon: _Optional[_Iterable[float]] = ...) -> None: ...

class TrackResult(_message.Message):
    __slots__ = ("track_id", "points", "routes", "splits", "length_m", "confidence", "error")
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    ROUTES_FIELD_NUMBER: _ClassVar[int]
    SPLITS_FIELD_NUMBER: _ClassVar[int]
    LENGTH_M_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    track_id: str
    points: _containers.RepeatedCompositeFieldContainer[MatchedPoint]
    routes: _containers.RepeatedCompositeFieldContainer[Route]
    splits: _containers.RepeatedScalarFieldContainer[int]
    length_m: float
    confidence: float
    error: Error
    def __init__(self, track_id: _Optional[str] = ..., points: _Optional[_Iterable[_Union[MatchedPoint, _Mapping]]] = ..., routes: _Optional[_Iterable[_Union[Route, _Mapping]]] = ..., splits: _Optional[_Iterable[int]] = ..., length_m: _Optional[float] = ..., confidence: _Optional[float] = ..., error: _Optional[_Union[Error, _Mapping]] = ...) -> None: ...

class ListMapsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListMapsResponse(_message.Message):
    __slots__ = ("maps", "default_map_id", "server_id")
    MAPS_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_MAP_ID_FIELD_NUMBER: _ClassVar[int]
    SERVER_ID_FIELD_NUMBER: _ClassVar[int]
    maps: _containers.RepeatedCompositeFieldContainer[MapInfo]
    default_map_id: str
    server_id: str
    def __init__(self, maps: _Optional[_Iterable[_Union[MapInfo, _Mapping]]] = ..., default_map_id: _Optional[str] = ..., server_id: _Optional[str] = ...) -> None: ...

class GetMapInfoRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class MapInfo(_message.Message):
    __slots__ = ("map_id", "min_lon", "min_lat", "max_lon", "max_lat", "node_count", "edge_count", "restriction_count", "road_km", "version", "checksum", "crs", "source", "build_parameters", "session_count")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    MIN_LON_FIELD_NUMBER: _ClassVar[int]
    MIN_LAT_FIELD_NUMBER: _ClassVar[int]
    MAX_LON_FIELD_NUMBER: _ClassVar[int]
    MAX_LAT_FIELD_NUMBER: _ClassVar[int]
    NODE_COUNT_FIELD_NUMBER: _ClassVar[int]
    EDGE_COUNT_FIELD_NUMBER: _ClassVar[int]
    RESTRICTION_COUNT_FIELD_NUMBER: _ClassVar[int]
    ROAD_KM_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    CHECKSUM_FIELD_NUMBER: _ClassVar[int]
    CRS_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    BUILD_PARAMETERS_FIELD_NUMBER: _ClassVar[int]
    SESSION_COUNT_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    min_lon: float
    min_lat: float
    max_lon: float
    max_lat: float
    node_count: int
    edge_count: int
    restriction_count: int
    road_km: float
    version: str
    checksum: str
    crs: str
    source: str
    build_parameters: _struct_pb2.Struct
    session_count: int
    def __init__(self, map_id: _Optional[str] = ..., min_lon: _Optional[float] = ..., min_lat: _Optional[float] = ..., max_lon: _Optional[float] = ..., max_lat: _Optional[float] = ..., node_count: _Optional[int] = ..., edge_count: _Optional[int] = ..., restriction_count: _Optional[int] = ..., road_km: _Optional[float] = ..., version: _Optional[str] = ..., checksum: _Optional[str] = ..., crs: _Optional[str] = ..., source: _Optional[str] = ..., build_parameters: _Optional[_Union[_struct_pb2.Struct, _Mapping]] = ..., session_count: _Optional[int] = ...) -> None: ...

class LoadMapRequest(_message.Message):
    __slots__ = ("map_id", "path")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    PATH_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    path: str
    def __init__(self, map_id: _Optional[str] = ..., path: _Optional[str] = ...) -> None: ...

class UnloadMapRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class UnloadMapResponse(_message.Message):
    __slots__ = ("sessions_dropped",)
    SESSIONS_DROPPED_FIELD_NUMBER: _ClassVar[int]
    sessions_dropped: int
    def __init__(self, sessions_dropped: _Optional[int] = ...) -> None: ...

class ExportSessionRequest(_message.Message):
    __slots__ = ("map_id", "vehicle_id", "remove")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_ID_FIELD_NUMBER: _ClassVar[int]
    REMOVE_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    vehicle_id: str
    remove: bool
    def __init__(self, map_id: _Optional[str] = ..., vehicle_id: _Optional[str] = ..., remove: _Optional[bool] = ...) -> None: ...

class SessionBlob(_message.Message):
    __slots__ = ("map_id", "vehicle_id", "map_checksum", "state")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_ID_FIELD_NUMBER: _ClassVar[int]
    MAP_CHECKSUM_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    vehicle_id: str
    map_checksum: str
    state: bytes
    def __init__(self, map_id: _Optional[str] = ..., vehicle_id: _Optional[str] = ..., map_checksum: _Optional[str] = ..., state: _Optional[bytes] = ...) -> None: ...

class ImportSessionRequest(_message.Message):
    __slots__ = ("session", "replace")
    SESSION_FIELD_NUMBER: _ClassVar[int]
    REPLACE_FIELD_NUMBER: _ClassVar[int]
    session: SessionBlob
    replace: bool
    def __init__(self, session: _Optional[_Union[SessionBlob, _Mapping]] = ..., replace: _Optional[bool] = ...) -> None: ...

class ImportSessionResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class EndSessionRequest(_message.Message):
    __slots__ = ("map_id", "vehicle_id")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    vehicle_id: str
    def __init__(self, map_id: _Optional[str] = ..., vehicle_id: _Optional[str] = ...) -> None: ...

class EndSessionResponse(_message.Message):
    __slots__ = ("existed",)
    EXISTED_FIELD_NUMBER: _ClassVar[int]
    existed: bool
    def __init__(self, existed: _Optional[bool] = ...) -> None: ...

class ListSessionsRequest(_message.Message):
    __slots__ = ("map_id", "vehicle_prefix", "limit")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_PREFIX_FIELD_NUMBER: _ClassVar[int]
    LIMIT_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    vehicle_prefix: str
    limit: int
    def __init__(self, map_id: _Optional[str] = ..., vehicle_prefix: _Optional[str] = ..., limit: _Optional[int] = ...) -> None: ...

class SessionSummary(_message.Message):
    __slots__ = ("map_id", "vehicle_id", "idle_seconds", "last_time")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    VEHICLE_ID_FIELD_NUMBER: _ClassVar[int]
    IDLE_SECONDS_FIELD_NUMBER: _ClassVar[int]
    LAST_TIME_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    vehicle_id: str
    idle_seconds: float
    last_time: float
    def __init__(self, map_id: _Optional[str] = ..., vehicle_id: _Optional[str] = ..., idle_seconds: _Optional[float] = ..., last_time: _Optional[float] = ...) -> None: ...

class ListSessionsResponse(_message.Message):
    __slots__ = ("sessions", "total")
    SESSIONS_FIELD_NUMBER: _ClassVar[int]
    TOTAL_FIELD_NUMBER: _ClassVar[int]
    sessions: _containers.RepeatedCompositeFieldContainer[SessionSummary]
    total: int
    def __init__(self, sessions: _Optional[_Iterable[_Union[SessionSummary, _Mapping]]] = ..., total: _Optional[int] = ...) -> None: ...
