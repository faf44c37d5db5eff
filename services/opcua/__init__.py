"""The OPC UA server of OPC 40100-1 (Machine Vision) that an MES drives: the OPC Foundation's NodeSet, one
VisionSystemType object per station, the Basic Vision System Server profile's mandatory methods backed by the
service, Basic256Sha256 Sign&Encrypt and API keys as users (docs/opcua.md).

- :mod:`services.opcua.server`: the address space, state machines, methods and events.
- :mod:`services.opcua.station`: recipes (part types), configurations (calibration sets), results (scans) and
  new scans, through the database.
- :mod:`services.opcua.security`: certificates, trusted clients, users and the scopes of the methods.
"""
