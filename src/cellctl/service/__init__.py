"""The running cell as a service: one owner per machine, and the control API every operator
surface goes through.

- :mod:`cellctl.service.functions`: every manual function of a machine, once.
- :mod:`cellctl.service.access`: a cell as the API sees it, attached to a running controller
  or standalone (the links opened here, holding their locks).
- :mod:`cellctl.service.methods`: the API's methods (JSON-RPC 2.0 names and parameters).
- :mod:`cellctl.service.params`: how a method is declared (its parameters' model, its entry).
- :mod:`cellctl.service.server`: the server ``cellctl run`` starts (WebSocket + HTTP GET).
- :mod:`cellctl.service.client`: how the CLI and the console reach a cell.
"""
