"""The link's services beyond telemetry and parameters, one module per service.

`log_download` (LOG_*: flights as archives), `ftp` and `ftp_wire` (MAVLink FTP: the server and
its wire format), `metadata` (COMPONENT_METADATA and the files it points to), `console`
(SERIAL_CONTROL shell) and `link_services`, which gives each link its own instance of each and
hands their answers to the link's paced sender. Services never import the link: what they need
of it is the `ServiceLink` protocol in `link_services`.
"""
