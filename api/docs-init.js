// Starts Swagger UI on the daemon's OpenAPI document (a file, not an inline script: the docs page's
// Content-Security-Policy allows scripts from the daemon only). Served at /api/v1/docs/docs-init.js.
/* global SwaggerUIBundle */
const root = document.getElementById("swagger-ui");
window.ui = SwaggerUIBundle({
  url: root.dataset.openapi,
  dom_id: "#swagger-ui",
  deepLinking: true,
  presets: [SwaggerUIBundle.presets.apis, SwaggerUIBundle.SwaggerUIStandalonePreset],
  layout: "BaseLayout",
  persistAuthorization: false,
  tryItOutEnabled: false,
});
