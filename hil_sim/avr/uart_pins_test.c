/* A tiny ATmega2560 program to test stage_harness without Marlin: UART0 at 250000 baud
 * echoes what it gets, except 'e' (prints E0/E1, the level of the X min endstop PE5) and
 * '+' / '-' (100 step pulses on PF0 with the direction on PF1, as RAMPS' X axis; prints S)
 * and 'h' (halts: sleeps with interrupts off, as a crashed firmware may). */
#include <avr/io.h>
#include <avr/interrupt.h>
#include <avr/sleep.h>
#include <util/delay.h>

static void put(char c)
{
	while (!(UCSR0A & (1 << UDRE0)))
		;
	UDR0 = c;
}

static char get(void)
{
	while (!(UCSR0A & (1 << RXC0)))
		;
	return UDR0;
}

int main(void)
{
	UCSR0A = 1 << U2X0;
	UBRR0 = F_CPU / 8 / 250000 - 1;  /* 7 at 16 MHz: exact */
	UCSR0B = (1 << RXEN0) | (1 << TXEN0);
	UCSR0C = (1 << UCSZ01) | (1 << UCSZ00);
	DDRF |= (1 << PF0) | (1 << PF1);
	DDRE &= ~(1 << PE5);
	for (;;) {
		char c = get();
		if (c == 'e') {
			put('E');
			put(PINE & (1 << PE5) ? '1' : '0');
			put('\n');
		} else if (c == '+' || c == '-') {
			if (c == '+')
				PORTF |= 1 << PF1;
			else
				PORTF &= ~(1 << PF1);
			for (int i = 0; i < 100; i++) {
				PORTF |= 1 << PF0;
				_delay_us(2);
				PORTF &= ~(1 << PF0);
				_delay_us(2);
			}
			put('S');
			put('\n');
		} else if (c == 'h') {
			cli();
			sleep_enable();
			sleep_cpu();
		} else {
			put(c);
		}
	}
}
