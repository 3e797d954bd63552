"""The benchmark behind ``geonet-infer bench`` and ``geonet-infer info``: its cases, the rows it
reports and the record of the machine. Not on the runtime's import path."""
