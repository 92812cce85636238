// Swagger UI on the service's own OpenAPI document: every file from this service, nothing from a CDN.
window.ui = SwaggerUIBundle({
  url: "/openapi.json",
  dom_id: "#swagger-ui",
  deepLinking: true,
  presets: [SwaggerUIBundle.presets.apis],
  layout: "BaseLayout",
  // no call to the public validator service (validator.swagger.io): the page works without internet
  validatorUrl: null,
});
