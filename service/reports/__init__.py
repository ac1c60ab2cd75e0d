"""Report generators above the runtime: `tactile bench`, `tactile model check`, `tactile model convergence`."""
