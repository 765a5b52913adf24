"""The command layer: `dmdsm` and one small module of subcommands per area, each a thin layer
over the API below. Nothing else imports it."""

