"""Tool-tissue contact and indentation measured from the registered clouds (issue 17)."""
