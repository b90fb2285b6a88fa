"""The dashboard's page: plain HTML, CSS and JavaScript in static/, served by hostd/api/web/."""
