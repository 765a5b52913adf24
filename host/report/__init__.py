"""Reports: figures like the paper's and the report page (the demo, host/demo/, writes them)."""
