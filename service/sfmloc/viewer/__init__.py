"""`sfmloc view`: a live web viewer of a map (its point cloud and cameras) and of every client
localizing against it (pose, recent trajectory, status, latency), fed by the Zenoh pose stream.

- ``mapdata``: what the page draws of a bundle (points, colours, cameras), read without the index
- ``live``: the Zenoh pose subscriber and the per-client state it keeps
- ``http``: the web server (stdlib ``http.server``): the page, the map, server-sent events
- ``static/``: the page (``index.html``, ``viewer.js``) and three.js, vendored (``vendor/``)

It observes: it reads bundles and pose messages, never the engine or the server's internals.
"""
