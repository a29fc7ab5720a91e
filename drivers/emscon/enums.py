"""The enumerations of Leica's ``ES_C_API_Def.h`` (emScon TPI/SDK 3.6) the driver uses.

Every ``ES_ResultStatus``, ``ES_Command``, ``ES_SystemStatusChange`` and ``ES_DataType`` value of
the V3.6 header; the other enums as far as the AT4xx extract (and CESAPI 1.1.3) list them. Names
drop the ``ES_XX_`` prefix; a leading digit becomes a word (``ES_RS_6DModeNotAllowed`` →
``SixDModeNotAllowed``).
"""

from __future__ import annotations

from enum import IntEnum

class DataType(IntEnum):
    """``ES_DataType``: what follows the packet header."""

    Command = 0
    Error = 1
    SingleMeasResult = 2
    MultiMeasResult = 3
    StationaryProbeMeasResult = 4
    ContinuousProbeMeasResult = 5
    NivelResult = 6
    ReflectorPosResult = 7
    SystemStatusChange = 8
    SingleMeasResult2 = 9
    MultiMeasResult2 = 10
    ProbePosResult = 11


class Cmd(IntEnum):
    """``ES_Command`` (V3.6; 50 and 141 are unassigned)."""

    ExitApplication = 0
    GetSystemStatus = 1
    GetTrackerStatus = 2
    SetTemperatureRange = 3
    GetTemperatureRange = 4
    SetUnits = 5
    GetUnits = 6
    Initialize = 7
    ReleaseMotors = 8
    ActivateCameraView = 9
    Park = 10
    SwitchLaser = 11
    SetStationOrientationParams = 12
    GetStationOrientationParams = 13
    SetTransformationParams = 14
    GetTransformationParams = 15
    SetBoxRegionParams = 16
    GetBoxRegionParams = 17
    SetSphereRegionParams = 18
    GetSphereRegionParams = 19
    SetEnvironmentParams = 20
    GetEnvironmentParams = 21
    SetRefractionParams = 22
    GetRefractionParams = 23
    SetMeasurementMode = 24
    GetMeasurementMode = 25
    SetCoordinateSystemType = 26
    GetCoordinateSystemType = 27
    SetStationaryModeParams = 28
    GetStationaryModeParams = 29
    SetContinuousTimeModeParams = 30
    GetContinuousTimeModeParams = 31
    SetContinuousDistanceModeParams = 32
    GetContinuousDistanceModeParams = 33
    SetSphereCenterModeParams = 34
    GetSphereCenterModeParams = 35
    SetCircleCenterModeParams = 36
    GetCircleCenterModeParams = 37
    SetGridModeParams = 38
    GetGridModeParams = 39
    SetReflector = 40
    GetReflector = 41
    GetReflectors = 42
    SetSearchParams = 43
    GetSearchParams = 44
    SetAdmParams = 45
    GetAdmParams = 46
    SetSystemSettings = 47
    GetSystemSettings = 48
    StartMeasurement = 49
    StartNivelMeasurement = 51
    StopMeasurement = 52
    ChangeFace = 53
    GoBirdBath = 54
    GoPosition = 55
    GoPositionHVD = 56
    PositionRelativeHV = 57
    PointLaser = 58
    PointLaserHVD = 59
    MoveHV = 60
    GoNivelPosition = 61
    GoLastMeasuredPoint = 62
    FindReflector = 63
    Unknown = 64
    LookForTarget = 65
    GetDirection = 66
    CallOrientToGravity = 67
    ClearTransformationNominalPointList = 68
    ClearTransformationActualPointList = 69
    AddTransformationNominalPoint = 70
    AddTransformationActualPoint = 71
    SetTransformationInputParams = 72
    GetTransformationInputParams = 73
    CallTransformation = 74
    GetTransformedPoints = 75
    ClearDrivePointList = 76
    AddDrivePoint = 77
    CallIntermediateCompensation = 78
    SetCompensation = 79
    SetStatisticMode = 80
    GetStatisticMode = 81
    GetStillImage = 82
    SetCameraParams = 83
    GetCameraParams = 84
    GetCompensation = 85
    GetCompensations = 86
    CheckBirdBath = 87
    GetTrackerDiagnostics = 88
    GetADMInfo = 89
    GetTPInfo = 90
    GetNivelInfo = 91
    SetLaserOnTimer = 92
    GetLaserOnTimer = 93
    ConvertDisplayCoordinates = 94
    GoBirdBath2 = 95
    SetTriggerSource = 96
    GetTriggerSource = 97
    GetFace = 98
    GetCameras = 99
    GetCamera = 100
    SetMeasurementCameraMode = 101
    GetMeasurementCameraMode = 102
    GetProbes = 103
    GetProbe = 104
    GetTipAdapters = 105
    GetTipAdapter = 106
    GetTCamToTrackerCompensations = 107
    GetTCamToTrackerCompensation = 108
    SetTCamToTrackerCompensation = 109
    GetProbeCompensations = 110
    GetProbeCompensation = 111
    SetProbeCompensation = 112
    GetTipToProbeCompensations = 113
    GetTipToProbeCompensation = 114
    SetExternTriggerParams = 115
    GetExternTriggerParams = 116
    GetErrorEllipsoid = 117
    GetMeasurementCameraInfo = 118
    GetMeasurementProbeInfo = 119
    SetLongSystemParameter = 120
    GetLongSystemParameter = 121
    GetMeasurementStatusInfo = 122
    GetCompensations2 = 123
    GetCurrentPrismPosition = 124
    SetDoubleSystemParameter = 125
    GetDoubleSystemParameter = 126
    GetObjectTemperature = 127
    GetTriggerBoardInfo = 128
    GetOverviewCameraInfo = 129
    ClearCommandQueue = 130
    GetADMInfo2 = 131
    GetTrackerInfo = 132
    GetNivelInfo2 = 133
    RestoreStartupConditions = 134
    GoAndMeasure = 135
    GetTipToProbeCompensations2 = 136
    SetTipAdapter = 137
    GetATRInfo = 138
    GetMeteoStationInfo = 139
    GetAT4xxInfo = 140
    GetSystemSoftwareVersion = 142


_OFF = 10000  # ES_API_ERROR_OFFSET


class Status(IntEnum):
    """``ES_ResultStatus``: every value of the V3.6 header (``ADMStartUpBusy`` is an alias)."""

    AllOK = 0
    ServerBusy = 1
    NotImplemented = 2
    WrongParameter = 3
    WrongParameter1 = 4
    WrongParameter2 = 5
    WrongParameter3 = 6
    WrongParameter4 = 7
    WrongParameter5 = 8
    WrongParameter6 = 9
    WrongParameter7 = 10
    Parameter1OutOfRangeOK = 11
    Parameter1OutOfRangeNOK = 12
    Parameter2OutOfRangeOK = 13
    Parameter2OutOfRangeNOK = 14
    Parameter3OutOfRangeOK = 15
    Parameter3OutOfRangeNOK = 16
    Parameter4OutOfRangeOK = 17
    Parameter4OutOfRangeNOK = 18
    Parameter5OutOfRangeOK = 19
    Parameter5OutOfRangeNOK = 20
    Parameter6OutOfRangeOK = 21
    Parameter6OutOfRangeNOK = 22
    WrongCurrentReflector = 23
    NoCircleCenterFound = 24
    NoSphereCenterFound = 25
    NoTPFound = 26
    NoWeathermonitorFound = 27
    NoLastMeasuredPoint = 28
    NoVideoCamera = 29
    NoAdm = 30
    NoNivel = 31
    WrongTPFirmware = 32
    DataBaseNotFound = 33
    LicenseExpired = 34
    UsageConflict = 35
    Unknown = 36
    NoDistanceSet = 37
    NoTrackerConnected = 38
    TrackerNotInitialized = 39
    ModuleNotStarted = 40
    ModuleTimedOut = 41
    ErrorReadingModuleDb = 42
    ErrorWritingModuleDb = 43
    NotInCameraPosition = 44
    TPHasServiceFirmware = 45
    TPExternalControl = 46
    WrongParameter8 = 47
    WrongParameter9 = 48
    WrongParameter10 = 49
    WrongParameter11 = 50
    WrongParameter12 = 51
    WrongParameter13 = 52
    WrongParameter14 = 53
    WrongParameter15 = 54
    WrongParameter16 = 55
    NoSuchCompensation = 56
    MeteoDataOutOfRange = 57
    InCompensationMode = 58
    InternalProcessActive = 59
    NoCopyProtectionDongleFound = 60
    ModuleNotActivated = 61
    ModuleWrongVersion = 62
    DemoDongleExpired = 63
    ParameterImportFromProbeFailed = 64
    ParameterExportToProbeFailed = 65
    TrkCompMeasCameraMismatch = 66
    NoMeasurementCamera = 67
    NoActiveMeasurementCamera = 68
    NoMeasurementCamerasInDb = 69
    NoCameraToTrackerCompSet = 70
    NoCameraToTrackerCompInDb = 71
    ProblemStoringCameraToTrackerFactorySet = 72
    ProblemWithCameraInternalCalibration = 73
    CommunicationWithMeasurementCameraFailed = 74
    NoMeasurementProbe = 75
    NoActiveMeasurementProbe = 76
    NoMeasurementProbesInDb = 77
    NoMeasurementProbeCompSet = 78
    NoMeasurementProbeCompInDb = 79
    ProblemStoringProbeFactorySet = 80
    WrongActiveMeasurementProbeCompInDb = 81
    CommunicationWithMeasurementProbeFailed = 82
    NoMeasurementTip = 83
    NoActiveMeasurementTip = 84
    NoMeasurementTipsInDb = 85
    NoMeasurementTipCompInDb = 86
    NoMeasurementTipCompSet = 87
    ProblemStoringTipAssembly = 88
    ProblemReadingCompensationDb = 89
    NoDataToImport = 90
    ProblemSettingTriggerSource = 91
    SixDModeNotAllowed = 92  # ES_RS_6DModeNotAllowed
    Bad6DResult = 93
    NoTemperatureFromWM = 94
    NoPressureFromWM = 95
    NoHumidityFromWM = 96
    SixDMeasurementFace2NotAllowed = 97  # ES_RS_6DMeasurementFace2NotAllowed
    InvalidInputData = 98
    NoTriggerBoard = 99
    NoMeasurementShankCompSet = _OFF + 1
    NoValidADMCompensation = _OFF + 2
    PressureSensorProblem = _OFF + 3
    MeasurementStatusNotReady = _OFF + 4
    AIFMStartUpBusy = _OFF + 5
    ADMStartUpBusy = _OFF + 5
    InvalidTipAdapter = _OFF + 6
    NoAtr = _OFF + 7
    NoOVC = _OFF + 8
    NoStationaryResult = _OFF + 9
    SensorNotLeveled = _OFF + 10
    MultiConnectionsNotAllowed = _OFF + 11
    SensorNotWarmedUp = _OFF + 12
    SensorNotStable = _OFF + 13
    SystemNotReadyForMeasurement = _OFF + 14
    CommunicationWithSensorFailed = _OFF + 15
    No_Sensor_Battery = _OFF + 16
    CompensatorNotAllowed = _OFF + 17
    WarmedUpStateReached = _OFF + 18
    NotLeveledForInitialization = _OFF + 19
    ADMHardwareProblem = _OFF + 20
    ATRHardwareProblem = _OFF + 21


class SSC(IntEnum):
    """``ES_SystemStatusChange``: unsolicited notifications (V3.6, the ``ES_SCC_`` typos kept as
    ``SCC_`` names)."""

    DistanceSet = 0
    LaserWarmedUp = 1
    EnvironmentParamsChanged = 2
    RefractionParamsChanged = 3
    SearchParamsChanged = 4
    AdmParamsChanged = 5
    UnitsChanged = 6
    ReflectorChanged = 7
    SystemSettingsChanged = 8
    TemperatureRangeChanged = 9
    CameraParamsChanged = 10
    CompensationChanged = 11
    CoordinateSystemTypeChanged = 12
    BoxRegionParamsChanged = 13
    SphereRegionParamsChanged = 14
    StationOrientationParamsChanged = 15
    TransformationParamsChanged = 16
    MeasurementModeChanged = 17
    StationaryModeParamsChanged = 18
    ContinuousTimeModeParamsChanged = 19
    ContinuousDistanceModeParamsChanged = 20
    GridModeParamsChanged = 21
    CircleCenterModeParamsChanged = 22
    SphereCenterModeParamsChanged = 23
    StatisticModeChanged = 24
    MeasStatus_NotReady = 25
    MeasStatus_Busy = 26
    MeasStatus_Ready = 27
    MeasurementCountReached = 28
    TriggerSourceChanged = 29
    IsFace1 = 30
    IsFace2 = 31
    ExternalControlActive = 32
    ServiceSoftwareActive = 33
    MeasurementCameraChanged = 34
    MeasurementCameraModeChanged = 35
    ProbeChanged = 36
    TipChanged = 37
    TCamToTrackerCompensationChanged = 38
    ProbeCompensationChanged = 39
    TipToProbeCompensationChanged = 40
    ExternTriggerParamsChanged = 41
    TCamToTrackerCompensationDeleted = 42
    MeasurementProbeCompensationDeleted = 43
    MeasurementTipCompensationDeleted = 44
    ManyMechanicalCompensationsInDB = 45
    MeasStatus_6DStatusInvalid = 99
    MeasurementProbeButtonDown = 100
    MeasurementProbeButtonUp = 101
    ExternalTriggerEvent = 102
    ExternalTriggerStartEvent = 103
    ExternalTriggerStopEvent = 104
    ObjectTemperatureChanged = 105
    OverviewCameraChanged = 106
    NivelSensorChanged = 107
    ProbeButton1Down = 110
    ProbeButton1Up = 111
    ProbeButton1DoubleClick = 112
    ProbeButton2Down = 120
    ProbeButton2Up = 121
    ProbeButton2DoubleClick = 122
    ProbeButton3Down = 130
    ProbeButton3Up = 131
    ProbeButton3DoubleClick = 132
    ProbeButton4Down = 140
    ProbeButton4Up = 141
    ProbeButton4DoubleClick = 142
    QuickReleaseOpend = 143
    QuickReleaseClosed = 144
    LaserReachingLimit = 145
    LaserNotStabilized = 146
    MultipleTipAdapterConnected = 150
    SCC_InitializationStatusChanged = 151
    SCC_TiltSensorStatusChanged = 152
    CompensationModeStart = 800
    CompensationModeEnd = 801
    EmsysFilesImported = 820
    SensorDetected = 850
    SensorDisconnected = 851
    CompensatorStatusChanged = 852
    BatteryStatusChanged = 853
    CopyProtectionRemoved = 996
    TPConnectionClosing = 997
    ServerClosing = 998
    ServerStarted = 999


class LengthUnit(IntEnum):
    Meter = 0
    Millimeter = 1
    Micron = 2
    Foot = 3
    Yard = 4
    Inch = 5


class AngleUnit(IntEnum):
    Radian = 0
    Degree = 1
    Gon = 2


class TemperatureUnit(IntEnum):
    Celsius = 0
    Fahrenheit = 1


class PressureUnit(IntEnum):
    Mbar = 0
    HPascal = 1
    KPascal = 2
    MmHg = 3
    Psi = 4
    InH2O = 5
    InHg = 6


class HumidityUnit(IntEnum):
    RH = 0


class CoordinateSystem(IntEnum):
    """``ES_CoordinateSystemType``: RHR = right-handed Cartesian x, y, z."""

    RHR = 0
    LHRX = 1
    LHRY = 2
    LHRZ = 3
    CCW = 4
    CCC = 5
    SCW = 6
    SCC = 7


class MeasMode(IntEnum):
    Stationary = 0
    ContinuousTime = 1
    ContinuousDistance = 2
    Grid = 3
    SphereCenter = 4
    CircleCenter = 5
    SixDStationary = 6
    SixDContinuousTime = 7
    SixDContinuousDistance = 8
    SixDGrid = 9
    SixDSphereCenter = 10
    SixDCircleCenter = 11


class TriggerStatus(IntEnum):
    """``ES_TriggerStatus``: the probe's trigger button in a 6-DoF result."""

    TriggerNotPressed = 0
    TriggerPressed = 1


class MeasurementTipStatus(IntEnum):
    """``ES_MeasurementTipStatus``: the probe's tip in a 6-DoF result."""

    TipOK = 0
    UnknownTip = 1
    MultipleTipsAttached = 2


class ProbeType(IntEnum):
    """``ES_ProbeType`` (``GetMeasurementProbeInfo``): a T-Mac is ``MachineControlProbe``."""

    None_ = 0  # ES_PT_None
    Reflector = 1
    TProbe = 2
    TScan = 3
    MachineControlProbe = 4
    MachineControlProbeMultiSide = 5
    TCamToTrackerTool = 100
    ZoomArtifactTool = 200


class ProbeConnectionType(IntEnum):
    """``ES_ProbeConnectionType``."""

    None_ = 0  # ES_PCT_None
    CableController = 1
    CableSensor = 2
    IRLaser = 3
    IRWideAngle = 4


class ProbeButtonType(IntEnum):
    """``ES_ProbeButtonType``."""

    None_ = 0  # ES_PBT_None
    Measurement = 1
    FourButton = 2  # ES_PBT_4Button


class TargetType(IntEnum):
    Unknown = 0
    CornerCube = 1
    CatsEye = 2
    GlassPrism = 3
    RFIPrism = 4
    RRR15 = 5
    RRR05 = 6
    BRR15 = 7
    BRR05 = 8
    TBR05 = 9


class TrackerStatus(IntEnum):
    NotReady = 0
    Busy = 1
    Ready = 2
    SixDStatusInvalid = 3


class SystemParameter(IntEnum):
    """``ES_SystemParameter`` values the AT4xx extract lists."""

    KeepLastPositionFlag = 0
    WeatherMonitorSetting = 1
    DisplayReflectorPosition = 10
    ProbeConfig_ButtonEvent = 51
    TcpCommandQueueSize = 200
    PowerLockFunctionAvailable = 410
    PowerLockFunctionActive = 411
    PowerLockMode = 450
    D_SystemLongest3DDistanceADM = 1101
    AT4xxControllerBatteryStatus = 5000
    AT4xxSensorBatteryStatus = 5001
    AT4xxInclinationSensorState = 5002


class WeatherMonitorStatus(IntEnum):
    NotConnected = 0
    ReadOnly = 1
    ReadAndCalculateRefractions = 2


class TrackerProcessorStatus(IntEnum):
    NoTPFound = 0
    TPFound = 1
    NBOpen = 2
    Booted = 3
    CompensationSet = 4
    Initialized = 5


class LaserProcessorStatus(IntEnum):
    LCPCommFailed = 0
    LCPNotAvail = 1
    LaserHeatingUp = 2
    LaserReady = 3
    UnableToStabilize = 4
    LaserOff = 5


class ADMStatus(IntEnum):
    NoADM = 0
    ADMCommFailed = 1
    ADMReady = 2
    ADMBusy = 3
    HWError = 4
    SecurityLockActive = 5
    NotCompensated = 6
