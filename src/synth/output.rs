//! Writing a synthetic scene directory (placeholder until the scene writers land).
