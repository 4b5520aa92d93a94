//! A CSV table read by the `csv` crate (quoted fields and all), with its
//! columns looked up by name: the service's recordings and exports.

use anyhow::Context;

/// A CSV text's header and rows.
#[derive(Debug, Clone)]
pub struct CsvTable {
    /// The header's column names.
    pub header: Vec<String>,
    /// The rows (a last row cut short, of a file still being written, is kept
    /// short: [`CsvTable::numbers`] then refuses it).
    pub rows: Vec<csv::StringRecord>,
}

impl CsvTable {
    /// Parses `text` (a header line, then rows).
    ///
    /// # Errors
    ///
    /// When the CSV header or a row cannot be read.
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let mut reader = csv::ReaderBuilder::new()
            .flexible(true)
            .from_reader(text.as_bytes());
        let header = reader
            .headers()
            .context("CSV header")?
            .iter()
            .map(str::to_owned)
            .collect();
        let rows = reader
            .records()
            .collect::<Result<Vec<_>, _>>()
            .context("CSV rows")?;
        Ok(Self { header, rows })
    }

    /// The index of column `name`.
    ///
    /// # Errors
    ///
    /// When there is no column `name`.
    pub fn column(&self, name: &str) -> anyhow::Result<usize> {
        self.header
            .iter()
            .position(|h| h == name)
            .with_context(|| format!("no column {name} in {:?}", self.header))
    }

    /// Column `name` as numbers (every row must parse).
    ///
    /// # Errors
    ///
    /// When there is no column `name` or a cell in it is not a number.
    pub fn numbers(&self, name: &str) -> anyhow::Result<Vec<f64>> {
        let i = self.column(name)?;
        self.rows
            .iter()
            .enumerate()
            .map(|(r, row)| {
                let cell = row.get(i).unwrap_or("");
                cell.parse::<f64>()
                    .with_context(|| format!("row {r}, column {name}: {cell:?} is not a number"))
            })
            .collect()
    }
}
