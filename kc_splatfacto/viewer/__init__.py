"""The browser viewer (viser): live while training (``kc-train --viewer``) and for finished runs (``kc-viewer``)."""
