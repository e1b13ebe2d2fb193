"""``scara-gui``: the paper's GUI (section 5.1) in a browser, live on Zenoh or on a recording."""
