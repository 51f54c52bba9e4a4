"""nn.Modules and their functional twins (denoisers, losses). Pure torch. Filled by their issues."""
