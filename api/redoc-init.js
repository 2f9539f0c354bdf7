// Starts ReDoc on the daemon's OpenAPI document (a file, not an inline script: the page's Content-Security-Policy
// allows scripts from the daemon only). Served at /api/v1/docs/redoc-init.js.
/* global Redoc */
const root = document.getElementById("redoc");
Redoc.init(root.dataset.openapi, { expandResponses: "200,202", hideDownloadButton: false }, root);
